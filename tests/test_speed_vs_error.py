"""Speed versus error (``scripts/speed_vs_error.py``, its analysis in ``scripts/lab/analysis.py``): Pareto front,
interpolation, ratios, crossovers, and a smoke run on a tiny procedural scene (both modes, two configurations)."""

from __future__ import annotations

import csv
import importlib.util
import json

import pytest

from conftest import REPO, load_script

TINY = [
    "scene.volume.procedural.resolution=16", "scene.camera.width=16", "scene.camera.height=9",
    "scene.integrator.max_scatter=4",
]


@pytest.fixture(scope="module")
def an():
    """The equal-time analysis the lab's tools share (scripts/lab/analysis.py)."""
    from lab import analysis

    return analysis


@pytest.fixture(scope="module")
def cli():
    """scripts/speed_vs_error.py, the command line."""
    return load_script("speed_vs_error")


def nrc_available() -> bool:
    return (REPO / "conf" / "renderer" / "nrc.yaml").is_file()


def test_pareto_and_loglog_interpolation(an):
    # a flat-time pt curve: 2 spp is no slower than 1 spp, so 1 spp leaves the front
    assert an.pareto([(1.0, 4.0), (0.9, 2.0), (2.0, 1.0), (2.5, 1.5)]) == [(0.9, 2.0), (2.0, 1.0)]
    # a point above the log-log line between its neighbours is not on the front
    assert an.pareto([(1.0, 8.0), (2.0, 7.9), (4.0, 1.0), (8.0, 0.6)]) == [(1.0, 8.0), (4.0, 1.0), (8.0, 0.6)]
    ts, es = [1.0, 4.0], [1.0, 0.25]
    assert an.loglog_interp(2.0, ts, es) == pytest.approx(0.5)
    assert an.loglog_interp(8.0, ts, es) == pytest.approx(0.125)  # slope -1 beyond the end
    assert an.loglog_interp(0.5, ts, es) == pytest.approx(1.0)  # flat before the fastest point


def test_equal_time_ratio_and_crossover(an):
    pt = [{"mode": m, "config": "pt", "renderer": "pt", "spp": 1, "frames": n, "time_s": float(n),
           "rel_mse": 1.0 / n, "rel_mse_medium": 2.0 / n} for m in ("single", "accumulate") for n in (1, 2, 4, 8)]
    # NRC: at t = 2 half of pt's error; accumulated, a bias floor of 0.3 (medium) that pt undercuts after t = 6.67
    nrc = [{"mode": "single", "config": "nrc", "renderer": "nrc", "spp": 1, "frames": 1, "time_s": 2.0,
            "rel_mse": 0.25, "rel_mse_medium": 0.5}]
    nrc += [{"mode": "accumulate", "config": "nrc", "renderer": "nrc", "spp": 1, "frames": n, "time_s": float(n),
             "rel_mse": 0.15, "rel_mse_medium": 0.3} for n in (1, 2, 4, 8)]
    (q,) = an.equal_time_ratios(pt + nrc, "pt")
    assert q["ratio_rel_mse"] == pytest.approx(0.5) and q["ratio_rel_mse_medium"] == pytest.approx(0.5)
    assert not q["extrapolated"]
    (c,) = an.crossovers(pt + nrc, "pt")
    assert c["metric"] == "rel_mse_medium" and c["pt_better_at_end"]
    assert 4.0 < c["crossover_time_s"] < 8.0 and not c["crossover_at_or_before"]
    # pt's first frame comes after NRC's first and already beats NRC at that time: "at or before" it, never
    # earlier (no pt image exists before its first frame)
    late_pt = [{**r, "time_s": r["time_s"] + 2.0, "rel_mse_medium": 0.01} for r in pt if r["mode"] == "accumulate"]
    (c,) = an.crossovers(late_pt + nrc, "pt")
    assert c["crossover_time_s"] == 3.0 and c["crossover_at_or_before"]


@pytest.mark.slow
def test_smoke_two_configs_both_modes(cli, tmp_path):
    second = ("nrc_tiny=renderer=nrc,encoding=triangle_oneblob,renderer.training.width=8,renderer.training.height=8,"
              "cache.network.n_neurons=16,cache.network.n_hidden_layers=2") if nrc_available() else \
        "pt_track=renderer=pt,transmittance=track_length"
    argv = ["--preset", "none", "--out", str(tmp_path / "out"), "--reference", str(tmp_path / "missing.exr"),
            "--configs", "pt", "--config", second, "--pt-spp", "1,2", "--repeats", "2", "--warmup", "1",
            "--frames", "2", "--acc-max-frames", "2", "--acc-repeats", "2",
            "--acc-pt-spp", "1", "--acc-configs", "all", "--acc-nrc-last", "--quiet", "--threads", "1", *TINY]
    # the reference: a small one rendered here, then passed explicitly
    from conftest import compose
    from nrc.evaluation.reference import render_reference

    render_reference(compose(TINY + ["scene.integrator.seed=1000000"]), tmp_path / "missing.exr", 8, 32,
                     progress=False)
    assert cli.main(argv) == 0
    out = tmp_path / "out"
    rows = list(csv.DictReader(open(out / "speed_vs_error.csv")))
    names = {r["config"] for r in rows}
    nrc_name = second.split("=")[0]
    assert names == {"pt", nrc_name} | ({nrc_name + ":last"} if nrc_available() else set())
    if nrc_available():  # NRC's frame alone beside its running mean: the same image after one frame
        acc = {(r["config"], int(r["frames"])): r for r in rows if r["mode"] == "accumulate"}
        assert acc[(nrc_name + ":last", 1)]["rel_mse"] == acc[(nrc_name, 1)]["rel_mse"]
        assert acc[(nrc_name + ":last", 2)]["rel_mse"] != acc[(nrc_name, 2)]["rel_mse"]
    assert {r["mode"] for r in rows} == {"single", "accumulate"}
    for r in rows:
        assert float(r["time_s"]) > 0 and float(r["rel_mse"]) >= 0 and r["rel_mse_medium"] != ""
    single_pt = [r for r in rows if r["config"] == "pt" and r["mode"] == "single"]
    assert [int(r["spp"]) for r in single_pt] == [1, 2] and all(float(r["variance"]) > 0 for r in single_pt)
    assert all(float(r["cpu_s"]) > 0 for r in rows if r["mode"] == "single")
    assert [int(r["frames"]) for r in rows if r["config"] == "pt" and r["mode"] == "accumulate"] == [1, 2]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["meta"]["baseline"] == ["pt"] and summary["meta"]["rel_mse_floor"] > 0
    md = (out / "speed_vs_error.md").read_text()
    assert "Single frames" in md and "Accumulated frames" in md
    assert (out / "speed_vs_error.png").stat().st_size > 1000
    assert all(r["rel_mse_corr"] == pytest.approx(r["rel_mse"] - summary["meta"]["rel_mse_floor"])
               for r in summary["rows"])
    (out / "speed_vs_error.md").unlink()
    assert cli.main(["--replot", str(out)]) == 0 and (out / "speed_vs_error.md").read_text() == md
    if nrc_available():
        single = [q for q in summary["equal_time"] if q["mode"] == "single"]
        assert len(single) == 1 and single[0]["ratio_rel_mse"] > 0
        assert [(q["config"], q["frames"]) for q in summary["equal_time"] if q["mode"] == "accumulate"] == [
            (nrc_name, 1), (nrc_name, 2), (nrc_name + ":last", 1), (nrc_name + ":last", 2)]
        assert len(summary["equal_cpu_time"]) == 1 and summary["equal_cpu_time"][0]["ratio_rel_mse"] > 0
        assert "Equal time per frame" in md


@pytest.mark.slow
def test_denoised_twins_and_both_baselines(cli, tmp_path):
    """--denoise: every single-frame configuration and every accumulated point gets a `+oidn` twin whose time
    includes the denoise time, and NRC is compared with both the raw and the denoised path tracer (equal-time
    ratios and crossovers); every row has its HDR-FLIP."""
    pytest.importorskip("pyoidn")
    from conftest import compose
    from nrc.evaluation.reference import render_reference

    render_reference(compose(TINY + ["scene.integrator.seed=1000000"]), tmp_path / "ref.exr", 8, 32, progress=False)
    nrc = ("nrc_tiny=renderer=nrc,encoding=triangle_oneblob,renderer.training.width=8,renderer.training.height=8,"
           "cache.network.n_neurons=16,cache.network.n_hidden_layers=2")
    argv = ["--preset", "none", "--out", str(tmp_path / "out"), "--reference", str(tmp_path / "ref.exr"),
            "--configs", "pt", "--config", nrc, "--pt-spp", "1,2", "--repeats", "2", "--warmup", "1", "--frames", "2",
            "--mode", "both", "--acc-configs", "all", "--acc-max-frames", "2", "--acc-repeats", "2",
            "--acc-pt-spp", "1", "--denoise", "--quiet", "--threads", "1", *TINY]
    assert cli.main(argv) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    acc = {(r["config"], r["frames"]): r for r in summary["rows"] if r["mode"] == "accumulate"}
    assert set(acc) == {(c, n) for c in ("pt", "pt+oidn", "nrc_tiny", "nrc_tiny+oidn") for n in (1, 2)}
    assert acc[("nrc_tiny+oidn", 2)]["time_s"] > acc[("nrc_tiny", 2)]["time_s"]
    crossed = {(c["config"], c["baseline"]) for c in summary["crossover"]}
    assert crossed == {("nrc_tiny", "pt"), ("nrc_tiny+oidn", "pt+oidn"), ("nrc_tiny", "pt+oidn")}
    if importlib.util.find_spec("flip_evaluator"):
        assert all(0 < r["flip"] < 1 for r in summary["rows"])
    rows = {(r["config"], r["spp"]): r for r in summary["rows"] if r["mode"] == "single"}
    assert set(c for c, _ in rows) == {"pt", "pt+oidn", "nrc_tiny", "nrc_tiny+oidn"}
    for (config, spp), r in rows.items():
        if config.endswith("+oidn"):
            raw = rows[(config[:-5], spp)]
            assert r["denoised"] and r["time_s"] == pytest.approx(raw["time_s"] + r["time_denoise_s"])
            assert r["rel_mse"] != raw["rel_mse"] and 0 < r["mean_ratio_medium"]
    against = {(q["config"], q["baseline"]) for q in summary["equal_time"]}
    assert against == {("nrc_tiny", "pt"), ("nrc_tiny+oidn", "pt+oidn"), ("nrc_tiny", "pt+oidn")}
    md = (tmp_path / "out" / "speed_vs_error.md").read_text()
    assert "| nrc_tiny+oidn | pt+oidn |" in md and "mean / reference, medium" in md


def test_equal_time_front_is_flat_where_more_time_did_not_help(an):
    """A denoised path tracer that is worse at 16 spp than at 4: at a time between the two the baseline is the
    4-spp error (a user would stop there), not an extrapolation below it."""
    base = [{"mode": "single", "config": "pt", "renderer": "pt", "spp": s, "time_s": t, "rel_mse": e}
            for s, t, e in ((1, 0.3, 0.004), (4, 0.5, 0.002), (16, 1.0, 0.006))]
    nrc = {"mode": "single", "config": "nrc", "renderer": "nrc", "spp": 1, "time_s": 0.8, "rel_mse": 0.01}
    (q,) = an.equal_time_ratios(base + [nrc], "pt")
    assert q["pt_rel_mse"] == pytest.approx(0.002) and q["ratio_rel_mse"] == pytest.approx(5.0)
    assert not q["extrapolated"]
    (q,) = an.equal_time_ratios(base + [{**nrc, "time_s": 2.0}], "pt")  # beyond every measured frame: ~ 1/time
    assert q["extrapolated"] and q["pt_rel_mse"] == pytest.approx(0.002 * 0.5 / 2.0)


@pytest.mark.slow
def test_animation_whole_run_smoke(tmp_path):
    """scripts/bench_animation.py on a tiny scene: all frames rendered, every k-th scored against its own
    reference (a sun that turns changes the reference), whole-run times and the path tracer's error at NRC's time."""
    bench = load_script("bench_animation")

    tiny = [*TINY, "scene=sun_sky", "renderer.backend=eager"]
    res = bench.animation(tiny, {"nrc": ["encoding=triangle_oneblob", "cache.network.n_neurons=16",
                                              "cache.network.n_hidden_layers=2", "renderer.training.width=8",
                                              "renderer.training.height=8"]},
                              [1, 2], frames=4, score_every=2, mode="sun", ref_spp=16, ref_chunk=8,
                              ref_dir=tmp_path, log=lambda *a: None)
    assert res["scored_frames"] == [1, 3] and len(list(tmp_path.glob("anim_*.exr"))) == 2
    pt1, pt2, nrc = res["rows"]
    assert (pt1["config"], pt2["config"], nrc["config"]) == ("pt", "pt", "nrc")
    for r in res["rows"]:
        assert r["whole_s"] > r["frame_s"] > 0 and r["whole_oidn_s"] >= r["whole_s"]
        assert r["rel_mse_medium"] > 0 and 0 < r["mean_ratio_medium"] < 10
    assert pt2["rel_mse_medium"] < pt1["rel_mse_medium"] * 1.5
    assert nrc["ratio_vs_pt"] == pytest.approx(nrc["rel_mse_medium"] / nrc["pt_rel_mse_medium"])
    assert "whole run" in bench.markdown(res)


def test_checkpoints_end_at_the_last_frame_and_accumulated_ratios(an, cli):
    assert cli.checkpoints(8) == [1, 2, 4, 8] and cli.checkpoints(30) == [1, 2, 4, 8, 16, 30]
    pt = [{"mode": "accumulate", "config": "pt", "renderer": "pt", "spp": 16, "frames": n, "time_s": 2.0 * n,
           "rel_mse": 1.0 / n} for n in (1, 2, 4, 8)]
    nrc = [{"mode": "accumulate", "config": "nrc", "renderer": "nrc", "spp": 1, "frames": 30, "time_s": 4.0,
            "rel_mse": 0.25}]
    assert an.equal_time_ratios(pt + nrc, "pt") == []  # single frames only by default
    (q,) = an.equal_time_ratios(pt + nrc, "pt", mode="accumulate")
    assert (q["mode"], q["frames"]) == ("accumulate", 30)
    assert q["pt_rel_mse"] == pytest.approx(0.5) and q["ratio_rel_mse"] == pytest.approx(0.5)
    assert [q["mode"] for q in an.all_ratios(pt + nrc, ["pt"])] == ["accumulate"]


def test_since_process_start_counts_the_imports(cli):
    t = cli.since_process_start()
    assert 0 < t < 24 * 3600  # this process started before the test (its imports take a while)


def test_jobs_arguments_are_stripped_from_the_jobs_command(cli):
    argv = ["--out", "o", "--jobs", "slurm", "--slurm", "partition=cpu", "--slurm=mem_gb=4", "--jobs=local", "x=1"]
    from lab.jobs import without_jobs

    assert without_jobs(argv) == ["--out", "o", "x=1"]
    assert cli.part_path("o", "pt") == __import__("pathlib").Path("o/configs/pt.json")


@pytest.mark.slow
def test_configurations_as_local_jobs_merge_like_one_process(cli, tmp_path):
    """--jobs local: each configuration a submitit job writing its rows; the merge writes the tables of one
    process (both configurations, ratios against the path tracer), a configuration's rows are not re-run, and rows
    of another machine type are refused."""
    pytest.importorskip("submitit")
    from conftest import compose
    from nrc.evaluation.reference import render_reference

    render_reference(compose(TINY + ["scene.integrator.seed=1000000"]), tmp_path / "ref.exr", 8, 16, progress=False)
    argv = ["--preset", "none", "--out", str(tmp_path / "out"), "--reference", str(tmp_path / "ref.exr"),
            "--configs", "pt", "--config", "pt_track=renderer=pt,transmittance=track_length", "--mode", "accumulate",
            "--acc-max-frames", "2", "--acc-repeats", "1", "--acc-pt-spp", "1", "--acc-configs", "all",
            "--acc-startup", "--quiet", "--threads", "1", "--jobs", "local", *TINY]
    assert cli.main(argv) == 0
    out = tmp_path / "out"
    parts = {p.stem: json.loads(p.read_text()) for p in (out / "configs").glob("*.json")}
    assert set(parts) == {"pt", "pt_track"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["meta"]["jobs"] == "local" and set(summary["meta"]["nodes"]) == {"pt", "pt_track"}
    assert "threads" in summary["meta"]["machine_type"]
    assert {(r["config"], r["frames"]) for r in summary["rows"]} == {(c, n) for c in ("pt", "pt_track") for n in (1, 2)}
    for r in summary["rows"]:  # start-up counted: the process's imports and the warm-up, then the render
        assert r["startup_counted"] and r["time_s"] == pytest.approx(r["render_s"] + r["startup_s"]
                                                                     + r["process_startup_s"])
        assert r["process_startup_s"] > 0
    assert "start-up included" in (out / "speed_vs_error.md").read_text()
    before = (out / "configs" / "pt.json").stat().st_mtime_ns
    parts["pt_track"]["meta"]["machine_type"] = "another CPU"
    (out / "configs" / "pt_track.json").write_text(json.dumps(parts["pt_track"]))
    with pytest.raises(SystemExit, match="speed_vs_error: .*pt_track on another CPU"):
        cli.main(argv)
    assert (out / "configs" / "pt.json").stat().st_mtime_ns == before  # not run again
