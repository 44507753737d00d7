"""scripts/make_figures.py end to end at a tiny size: every figure is written and its numbers agree."""

import importlib.util
import json

import numpy as np
import pytest

pytest.importorskip("imageio")


@pytest.mark.slow
def test_make_figures_writes_every_figure_with_consistent_numbers(tmp_path):
    from PIL import Image, ImageSequence

    from conftest import load_script

    figures = load_script("make_figures")
    HEROES, SHARED_VDB = figures.HEROES, figures.SHARED_VDB
    log = figures.main(["--out", str(tmp_path / "img"), "--ref-dir", str(tmp_path / "refs"), "--hero-width", "24",
                "--hero-height", "14", "--hero-spp", "4", "--chunk-spp", "2", "--width", "64", "--height", "36",
                "--spp", "1", "--frames", "3", "--ref-spp", "8", "--anim-frames", "3", "--anim-warmup", "1",
                "--backend", "eager", "--comparison", "default"])
    out = tmp_path / "img"
    heroes = [h for h in HEROES if h != "disney" or SHARED_VDB.is_file()]
    assert sorted(log["heroes"]) == sorted(heroes)
    sheet = np.asarray(Image.open(out / "clouds.png"))
    assert sheet.shape[1] == 2 * 24 + 4 and sheet.shape[0] >= 14
    comparison = json.loads((out / "nrc_vs_pt.json").read_text())
    assert comparison == log["comparison"]
    assert comparison["pt"]["spp"] >= 1 and comparison["nrc"]["frames"] == 3
    sides = ("pt", "nrc", "pt_oidn", "nrc_oidn") if importlib.util.find_spec("pyoidn") else ("pt", "nrc")
    for side in sides:
        assert np.isfinite(comparison[side]["rel_mse_medium"]) and comparison[side]["mean_over_reference_medium"] > 0
    # one panel per image and the reference, each 2 x 64 pixels wide (figsize w / 50 inches at 100 dpi)
    assert np.asarray(Image.open(out / "nrc_vs_pt.png")).shape[1] == (len(sides) + 1) * 2 * 64
    frames = [f.copy() for f in ImageSequence.Iterator(Image.open(out / "sun.webp"))]
    assert len(frames) == 3 and frames[0].size == (2 * 64 + 2, 36)
    assert json.loads((out / "figures.json").read_text())["time_total_s"] > 0
    assert len(list((tmp_path / "refs").glob("*.exr"))) == len(heroes) + 1
