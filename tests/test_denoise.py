"""The denoiser wrapper (pyoidn) and `denoise=oidn` in the app."""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO
from nrc.errors import ConfigError, NRCError

pyoidn = pytest.importorskip("pyoidn")


def noisy_image(seed=0, h=48, w=64):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    clean = np.stack([0.2 + 0.5 * xx, 0.3 + 0.4 * yy, 0.5 + 0.0 * xx], -1).astype(np.float32)
    return clean, (clean * rng.exponential(1.0, size=clean.shape)).astype(np.float32)


def test_denoise_removes_noise_and_is_deterministic():
    from nrc.denoise import denoise

    clean, noisy = noisy_image()
    noisy[3, 4] = np.nan  # cleaned in OIDN's copy only
    noisy[5, 6] = -1.0
    raw = noisy.copy()
    a, b = denoise(noisy), denoise(noisy)
    assert a.shape == noisy.shape and a.dtype == np.float32 and np.isfinite(a).all()
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.isnan(noisy), np.isnan(raw))  # the input is untouched
    err_noisy = np.nanmean((np.nan_to_num(noisy) - clean) ** 2)
    assert np.mean((a - clean) ** 2) < 0.25 * err_noisy
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        denoise(noisy[..., :2])


def test_denoise_setting_is_validated(monkeypatch):
    from nrc import denoise as mod

    with pytest.raises(ConfigError, match="denoise must be one of"):
        mod.denoiser_from_config({"denoise": "bm3d"})
    assert mod.denoiser_from_config({}) == "none"
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # as if the extra were not installed
    with pytest.raises(NRCError, match=r"pip install pyoidn .*or run with denoise=none"):
        mod.denoiser_from_config({"denoise": "oidn"})


def test_app_writes_the_denoised_image_beside_the_raw_one(tmp_path):
    from nrc.io import read_exr

    proc = subprocess.run([sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path}", "renderer=pt", "denoise=oidn",
                           "scene.volume.procedural.resolution=16", "scene.camera.width=16", "scene.camera.height=9"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    raw, _ = read_exr(tmp_path / "image.exr")
    den, attrs = read_exr(tmp_path / "image_denoised.exr")
    assert raw.shape == den.shape == (9, 16, 3) and not np.array_equal(raw, den)
    assert attrs["denoiser"].startswith("pyoidn")
    assert (tmp_path / "preview_denoised.png").is_file()
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["time_denoise_s"] > 0 and metrics["denoise"].startswith("pyoidn")


def test_clamp_bias_measures_what_cleaning_negative_pixels_adds():
    from nrc.denoise import clamp_bias

    img = np.full((4, 4, 3), 1.0, np.float32)
    assert clamp_bias(img) == 0.0
    img[0, 0] = -2.0  # raw mean (15 - 2) / 16, clean mean 15 / 16
    assert clamp_bias(img) == pytest.approx((15 / 16 - 13 / 16) / (13 / 16))
    img[1, 1] = np.nan  # non-finite values count as 0 on both sides
    assert clamp_bias(img) == pytest.approx((14 / 16 - 12 / 16) / (12 / 16))
