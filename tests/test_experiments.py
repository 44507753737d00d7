"""The thesis experiments: conf/experiment/*.yaml compose, and the reports (``scripts/experiments_report.py``)
on hand-made runs."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from conftest import CONF_DIR, load_script

# the thesis experiments (multiruns with a report); bench_* are single-run benchmark configs
EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml") if not p.stem.startswith("bench_"))


def test_canonical_benchmark_config_is_the_documented_scene():
    """``+experiment=bench_canonical`` (docs/measurements/speed.md): independent of the scene presets."""
    cfg = compose_experiment("bench_canonical")
    v, c, (light,) = cfg.scene.volume, cfg.scene.camera, cfg.scene.lights
    assert v.path.endswith("wdas_cloud_sixteenth.vdb") and list(v.center) == [0, 0, 0] and v.diagonal == 107.5
    assert (v.density_scale, v.albedo, v.g) == (0.6, 1.0, 0.8)
    assert list(c.position) == [64, 0, 0] and list(c.look_at) == [0, 0, 0] and c.fov_y == 60
    assert (c.width, c.height, cfg.scene.integrator.spp, cfg.scene.integrator.max_scatter) == (128, 72, 512, 64)
    assert light.type == "directional" and list(light.direction) == [0, 0, -1] and list(light.irradiance) == [16] * 3
    assert cfg.renderer.name == "pt" and not cfg.renderer.russian_roulette.enabled


def compose_experiment(name: str, overrides: list[str] | None = None):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        # the sweeper puts the swept overrides before the command line's +experiment=... (as here)
        return compose(config_name="config", overrides=[*(overrides or []), f"+experiment={name}"],
                       return_hydra_config=True)


@pytest.fixture(scope="module")
def report():
    return load_script("experiments_report")


def test_every_report_has_its_experiments(report):
    assert sorted(e for exps in report.REPORTS.values() for e in exps) == EXPERIMENTS


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_as_a_multirun(name):
    cfg = compose_experiment(name)
    assert cfg.hydra.mode.name == "MULTIRUN"
    assert cfg.experiment_name == name
    assert cfg.scene.volume.source == "vdb" and cfg.scene.volume.path.endswith("wdas_cloud_sixteenth.vdb")
    params = cfg.hydra.sweeper.params
    assert len(params) >= 1
    # every swept value composes (group options exist, framings/setups resolve)
    for key, values in params.items():
        for v in str(values).split(","):
            sub = compose_experiment(name, [f"{key}={v}"])
            if key.startswith("experiment/framing"):
                assert sub.framing == v
            if "setup" in key:
                assert sub.setup == v
                assert sub.scene.volume.density_scale == (0.25 if v.endswith("025") else 0.6)
                assert sub.scene.lights[0].type == ("point" if v.startswith("point") else "directional")
            if key == "encoding":
                assert sub.encoding.position.otype


def test_framings_include_one_without_the_cloud():
    from nrc.metrics import medium_mask
    from nrc.render.preview import medium_alpha
    from nrc.scene import load_scene

    seen = {}
    for framing in ("full", "empty"):
        cfg = compose_experiment("batch_filters", [f"experiment/framing@_global_={framing}", "scene.volume.source=procedural",
                                                   "scene.volume.path=null", "scene.volume.procedural.resolution=16",
                                                   "scene.camera.width=16", "scene.camera.height=9"])
        seen[framing] = medium_mask(medium_alpha(load_scene(cfg.scene))).mean()
    assert seen["full"] > 0.2 and seen["empty"] == 0.0


def fake_run(job, cfg, renderer: str, image: np.ndarray, metrics: dict, choices: dict) -> None:
    from nrc.io import write_exr

    (job / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, job / ".hydra" / "config.yaml")
    OmegaConf.save(OmegaConf.create([f"renderer={renderer}"]), job / ".hydra" / "overrides.yaml")
    OmegaConf.save(OmegaConf.create({"hydra": {"runtime": {"choices": choices}}}), job / ".hydra" / "hydra.yaml")
    write_exr(job / "image.exr", image)
    (job / "metrics.json").write_text(json.dumps(metrics))


def test_report_on_hand_made_runs(report, tmp_path, monkeypatch):
    from conftest import compose
    from nrc.config import scene_hash
    from nrc.evaluation.reference import write_reference_exr

    cfg = compose(["scene.camera.width=4", "scene.camera.height=3"])
    OmegaConf.set_struct(cfg, False)
    cfg.setup = "sun_06"
    ref = np.full((3, 4, 3), 0.5, np.float32)
    alpha = np.zeros((3, 4), np.float32)
    alpha[:, :2] = 0.9  # the medium: the left half
    monkeypatch.setattr(report, "REF_DIR", tmp_path / "refs")
    (tmp_path / "refs").mkdir()
    write_reference_exr(tmp_path / "refs" / f"reference_{scene_hash(cfg)[:12]}_64spp.exr", ref, alpha,
                        {"spp": 64, "rel_mse_floor": 1e-4, "rel_mse_floor_medium": 2e-4})
    root = tmp_path / "multirun"
    # pt: unbiased, +-0.1 around the reference; nrc: biased by +0.2, no noise; 2 seeds each
    for i, (renderer, img) in enumerate([("pt", ref + 0.1), ("pt", ref - 0.1), ("nrc", ref + 0.2), ("nrc", ref + 0.2)]):
        c = cfg.copy()
        c.renderer.name = renderer
        exp = "nrc_vs_pt_pt" if renderer == "pt" else "nrc_vs_pt_nrc"
        metrics = {"time_render_s": 2.0} if renderer == "pt" else {
            "frame_times_s": [5.0, 1.0, 1.0], "loss_per_frame": [3.0, 2.0, 1.0], "time_train_s": [1, 0.5, 0.5]}
        fake_run(root / exp / str(i), c, renderer, img, metrics, {"renderer": renderer})
    cli = report  # the module whose REF_DIR is patched above
    assert cli.main(["nrc_vs_pt", "--root", str(root), "--docs", str(tmp_path / "docs")]) == 0
    md = (tmp_path / "docs" / "results" / "nrc_vs_pt.md").read_text()
    rows: dict[str, list[str]] = {}
    for line in md.splitlines():  # the first (medium pixels) table
        if line.startswith("| sun_06"):
            rows.setdefault(line.split("|")[2].strip(), [c.strip() for c in line.split("|")[3:-1]])
    # columns: seeds, time, MSE, relMSE, rel. bias, rel. variance, thesis rBias, thesis rVar, reference spp
    pt, nrc = rows["pt"], rows["nrc"]
    assert pt[0] == "2" and float(pt[1]) == 2.0 and float(nrc[1]) == 1.0  # nrc: frame 0 (start-up) left out
    assert float(pt[2]) == pytest.approx(0.01, rel=1e-4) and float(nrc[2]) == pytest.approx(0.04, rel=1e-4)
    assert float(pt[4]) == pytest.approx(0.0, abs=1e-6)  # the seeds' errors cancel in the per-pixel mean
    assert float(nrc[4]) == pytest.approx(0.2 / 0.51, rel=1e-3) and float(nrc[5]) == 0.0
    assert float(pt[5]) == pytest.approx(0.02 / 0.26, rel=1e-3)  # var over 2 seeds (ddof 1): 0.02
    assert float(nrc[6]) == pytest.approx(0.4, rel=1e-3) and pt[8] == "64"
    assert "python -m nrc +experiment=nrc_vs_pt_pt" in md
    # results.md: the intro, speed sections (missing here) and the reports
    (tmp_path / "intro.md").write_text("Hand-written intro.")
    assert cli.main(["nrc_vs_pt", "--root", str(root), "--docs", str(tmp_path / "docs"), "--results",
                     "--intro", str(tmp_path / "intro.md")]) == 0
    results = (tmp_path / "docs" / "results.md").read_text()
    # the hand-written page linked, not copied; each report linked to its own page
    assert "intro.md) (hand-written)" in results and "Hand-written intro." not in results
    assert "docs/results/oidn_480x270_side_lit/summary.json` is missing" in results
    assert "[nrc_vs_pt](results/nrc_vs_pt.md)" in results and "equal-time relMSE ratio" not in results


def test_headline_is_nrc_plus_oidn_against_pt_plus_oidn_with_the_bias():
    """The results page's headline: the side-lit run's NRC + OIDN over PT + OIDN ratio at equal time, NRC + OIDN's
    image mean beside it, the raw ratio, and the same ratio of every other scene-type run."""
    report = load_script("experiments_report")
    headline, scene_type_table = report.headline, report.scene_type_table

    def run(ratio_den, mean):
        rows = [{"mode": "single", "config": "nrc+oidn", "renderer": "nrc", "denoised": True, "time_s": 0.3,
                 "mean_ratio_medium": mean},
                {"mode": "single", "config": "pt+oidn", "renderer": "pt", "denoised": True, "time_s": 0.31,
                 "mean_ratio_medium": 0.99}]
        ratios = [{"config": "nrc+oidn", "baseline": "pt+oidn", "time_s": 0.3, "ratio_rel_mse_medium": ratio_den,
                   "pt_rel_mse_medium": 0.004},
                  {"config": "nrc", "baseline": "pt", "time_s": 0.29, "ratio_rel_mse_medium": 0.12,
                   "pt_rel_mse_medium": 0.4}]
        return {"rows": rows, "equal_time": ratios}

    text = " ".join(headline({"oidn_160x90_side_lit": ("side-lit", run(4.5, 0.962)),
                              "oidn_160x90_cumulus": ("cumulus", run(2.25, 1.05))}))
    assert "relMSE ratio **4.5**" in text and "**0.962** of the reference" in text
    assert "raw path tracer: 0.12" in text and "cumulus: 2.2 (mean 1.05)" in text
    assert headline({"speed_160x90_v2": ("old", run(1.0, 1.0))}) == []
    table = scene_type_table({"oidn_160x90_cumulus": ("cumulus", {**run(2.25, 1.05), "meta": {"argv": ["--warmup", "30"]}})})
    assert len(table) == 4 and "| cumulus, 30 warm-up frames | 0.12 | **2.2** |" in table[2]
