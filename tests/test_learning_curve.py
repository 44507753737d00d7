"""scripts/learning_curve.py: the interval over seeds, the crossing frame, the outputs' shape (fast), and one tiny run
end to end (slow)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, SHARED_VDB, load_script


@pytest.fixture(scope="module")
def lc():
    return load_script("learning_curve")


def test_the_interval_is_the_t_quantile_times_the_standard_error(lc):
    mean, half = lc.ci95([1.0, 2.0, 3.0, 4.0, 5.0])
    # t_{0.975, 4} = 2.776445; standard error sqrt(2.5 / 5)
    assert mean == pytest.approx(3.0)
    assert half == pytest.approx(2.776445 * math.sqrt(2.5 / 5), rel=1e-5)
    mean, half = lc.ci95([2.0, 4.0])  # t_{0.975, 1} = 12.7062, standard error 1
    assert (mean, half) == (pytest.approx(3.0), pytest.approx(12.7062, rel=1e-4))
    assert lc.ci95([7.0]) == (7.0, None)  # one seed: no interval


@pytest.mark.parametrize("curve, pt, frame", [
    ([5.0, 3.0, 1.0, 0.5], 1.0, 3),  # equal counts as crossed
    ([0.1, 0.2, 0.3, 0.4], 1.0, 1),  # below from the start
    ([0.5, 2.0, 0.8, 0.9], 1.0, 3),  # dips below, back above, then stays below
    ([0.5, 0.5, 2.0], 1.0, None),  # ends above: never stays below
    ([2.0, 2.0, 2.0], 1.0, None),  # never crosses
    ([0.5, 0.5], None, None),  # no path tracer value
    ([0.5, float("nan"), 0.5], 1.0, 3),  # a NaN is not below
])
def test_the_crossing_frame_is_the_first_from_which_nrc_stays_below(lc, curve, pt, frame):
    frames = [1, 5, 10, 15][:len(curve)]
    assert lc.crossing_frame(frames, curve, pt) == (None if frame is None else frames[frame - 1])


def test_scored_frames_hold_the_first_every_kth_and_the_last(lc):
    assert lc.scored_frames(3, 1) == [1, 2, 3]
    assert lc.scored_frames(30, 10) == [1, 10, 20, 30]
    assert lc.scored_frames(7, 3) == [1, 3, 6, 7]
    assert lc.scored_frames(1, 5) == [1]


def fake_result(lc, point="d5", frames=30, every=10, seeds=3):
    marks = lc.scored_frames(frames, every)
    rng = np.random.default_rng(0)
    per_seed = [[{"rel_mse": 1.0 / f + 0.01 * rng.random(), "rel_mse_oidn": 0.4 / f + 0.001 * rng.random(),
                  "mean_ratio": 1 - 0.1 / f, "mean_ratio_oidn": 1 - 0.1 / f + 0.001 * s} for f in marks]
                for s in range(seeds)]
    curve = lc.curve_rows(marks, per_seed, 0.05)
    cross = lc.crossing_frame(marks, [r["rel_mse_oidn"] for r in curve], 0.05)
    return {"point": point, "curve": curve, "crossing_frame": cross,
            "nrc_frame_s": 0.2, "oidn_s": 0.01, "equal_time_s": 0.21, "pt_frame_s": {1: 0.1},
            "pt_oidn": {"rel_mse": 0.05, "rel_mse_ci": 0.01, "extrapolated": False}, "pt_raw_rel_mse": 0.3,
            "backend": {"requested": "auto", "nrc": "eager", "pt": "eager"},
            "reference": {"path": "data/references/x.exr", "spp": 1024, "rel_mse_floor_medium": 1e-4},
            "settings": {"width": 160, "height": 90, "frames": frames, "every": every, "seeds": seeds, "nrc_spp": 1,
                         "pt_spp": [1, 2, 4], "pt_repeats": 3, "label": "default", "nrc_overrides": [], "scene": [],
                         "ref_spp": 1024},
            "machine": "CPU, 2 cores", "argv": []}


def test_the_curve_rows_table_json_and_summary(lc, tmp_path):
    res = fake_result(lc)
    rows = res["curve"]
    assert [r["frame"] for r in rows] == [1, 10, 20, 30]
    assert rows[1]["ratio_oidn"] == pytest.approx(rows[1]["rel_mse_oidn"] / 0.05)
    assert all(r["rel_mse_oidn_ci"] > 0 for r in rows) and rows[0]["mean_ratio_ci"] == pytest.approx(0.0, abs=1e-12)
    assert res["crossing_frame"] == 10  # 0.4 / f + at most 0.001 <= 0.05 from frame 10 on
    lc.write_point(res, tmp_path / "d5")
    lc.write_point(fake_result(lc, "d2", frames=5, every=1), tmp_path / "d2")
    for name in ("curve.json", "curve.md", "curve.png"):
        assert (tmp_path / "d5" / name).stat().st_size > 0
    assert json.loads((tmp_path / "d5" / "curve.json").read_text())["curve"] == json.loads(json.dumps(rows))
    table = (tmp_path / "d5" / "curve.md").read_text().splitlines()
    rows_md = [line for line in table if line.startswith("| ") and line[2].isdigit()]
    assert len(rows_md) == 4 and all(line.count("|") == 8 for line in rows_md)
    assert "±" in rows_md[0] and "crosses PT+OIDN at frame **10**" in "\n".join(table)
    summary = lc.write_summary(tmp_path).read_text().splitlines()
    d2 = next(line for line in summary if line.startswith("| d2 "))
    d5 = next(line for line in summary if line.startswith("| d5 "))
    assert d2.split("|")[5].strip() == "–"  # d2 has no frame 10
    assert float(d5.split("|")[5]) == pytest.approx(rows[1]["ratio_oidn"], rel=0.05)


def test_the_summary_follows_the_points_order_and_the_comparison_puts_variants_side_by_side(lc, tmp_path):
    """Points in the crossover map's order (thin to thick), not by name; one comparison row per point and
    variant, the default first, each variant's ratios read off its own curve."""
    for label, scale, folder in (("default", 1.0, "default"), ("faster", 0.5, "faster"),
                                 ("default", 1.0, "renamed")):  # an earlier default kept under another folder
        for point in ("d10", "d0.6", "d5"):
            res = fake_result(lc, point)
            res["settings"] = {**res["settings"], "label": label, "nrc_overrides": [] if label == "default" else ["x=1"]}
            for r in res["curve"]:
                r["ratio_oidn"] *= scale
                r["rel_mse_oidn"] *= scale
            lc.write_point(res, tmp_path / folder / point)
    summary = lc.write_summary(tmp_path / "default").read_text()
    assert summary.index("| d0.6 ") < summary.index("| d5 ") < summary.index("| d10 ")
    rows = [line for line in lc.write_comparison(tmp_path).read_text().splitlines() if line.startswith("| d")]
    assert [(r.split("|")[1].strip(), r.split("|")[2].strip()) for r in rows] == [
        (p, v) for p in ("d0.6", "d5", "d10") for v in ("default", "faster", "renamed")]
    default, faster = rows[0].split("|"), rows[1].split("|")
    assert faster[3].strip() == "x=1" and default[3].strip() == "–"
    def cell(row):  # "relMSE (ratio)" @10
        err, ratio = row[7].split()
        return float(err), float(ratio.strip("()"))

    assert cell(faster) == pytest.approx(tuple(x / 2 for x in cell(default)), rel=0.05)


def test_an_unknown_point_is_refused(lc):
    with pytest.raises(SystemExit, match="unknown point 'd7'.*known: d0.35"):
        lc.main(["--points", "d7"])


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_VDB.is_file(), reason="the Disney cloud is absent")
def test_a_tiny_run_end_to_end(tmp_path):
    """The whole tool on the thinnest point (its short paths: a fifth of d5's time, the same code): the curve's
    files and numbers, the summary's row, and a second call that renders nothing."""
    env = {**os.environ, "NRC_REFERENCE_DIR": str(tmp_path / "refs")}
    cmd = [sys.executable, str(REPO / "scripts" / "learning_curve.py"), "--points", "d0.35", "--width", "16",
           "--height", "9", "--frames", "3", "--seeds", "2", "--ref-spp", "16", "--pt-spp", "1", "--pt-repeats", "2",
           "--out", str(tmp_path / "out"), "--quiet"]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    point = tmp_path / "out" / "d0.35"
    for name in ("curve.json", "curve.md", "curve.png"):
        assert (point / name).stat().st_size > 0, name
    res = json.loads((point / "curve.json").read_text())
    assert [r["frame"] for r in res["curve"]] == [1, 2, 3] and len(res["nrc_per_seed"]) == 2
    numbers = [r[k] for r in res["curve"] for k in ("rel_mse", "rel_mse_oidn", "mean_ratio", "mean_ratio_oidn",
                                                   "rel_mse_ci", "rel_mse_oidn_ci", "pt_oidn_rel_mse", "ratio_oidn")]
    numbers += [res["nrc_frame_s"], res["oidn_s"], res["pt_oidn"]["rel_mse"], res["reference"]["rel_mse_floor_medium"]]
    assert all(isinstance(x, float) and math.isfinite(x) for x in numbers), numbers
    assert res["reference"]["spp"] == 16 and res["backend"]["nrc"] in ("eager", "compiled")
    assert res["crossing_frame"] in (None, 1, 2, 3) and res["machine"] and res["argv"]
    assert "| d0.35 | default | 2 |" in (tmp_path / "out" / "summary.md").read_text()
    again = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)  # not run again
    assert again.returncode == 0 and "done in" not in again.stdout, again.stderr[-3000:]


def test_a_signal_that_stopped_the_nrc_run_ends_the_lab_tool_with_one_line(lc, capsys):
    """The NRC renderer stops after the current frame on SIGINT / SIGTERM and returns; the lab tools then exit with
    the signal's code and one line (``lab.render.stopped_by``), instead of scoring frames never rendered (an
    IndexError before)."""
    from lab.render import stopped_by

    stopped_by({"interrupted": None, "frames_done": 30}, 30)  # a run that finished: nothing
    for sig, code in (("SIGTERM", 143), ("SIGINT", 130)):
        with pytest.raises(SystemExit) as exc:
            stopped_by({"interrupted": sig, "frames_done": 7}, 30)
        assert exc.value.code == code
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"stopped by {sig} after 7 of 30 NRC frames" in err[0]
