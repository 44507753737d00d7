"""The benchmark configs of conf/experiment/ (the theses' experiments: tests/test_theses.py) and the results page's
headline (``scripts/experiments_report.py``)."""

from __future__ import annotations

from conftest import CONF_DIR, load_script


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
