"""EXR round trip (with header attributes) and PNG previews."""

import numpy as np
import pytest

from nrc.errors import NRCError
from nrc.io import read_exr, tonemap, write_exr, write_png


def test_exr_round_trip_is_lossless_float32(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.random((7, 11, 3)) * 100).astype(np.float32)
    write_exr(tmp_path / "a.exr", img, {"spp": 64, "config_hash": "deadbeef"})
    back, attrs = read_exr(tmp_path / "a.exr")
    assert back.dtype == np.float32 and back.shape == (7, 11, 3)
    np.testing.assert_array_equal(back, img)
    assert attrs["spp"] == 64 and attrs["config_hash"] == "deadbeef"


def test_read_exr_errors(tmp_path):
    with pytest.raises(NRCError, match="not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"garbage")
    with pytest.raises(NRCError, match="not a readable EXR"):
        read_exr(tmp_path / "bad.exr")


def test_tonemap_shows_nan_and_inf_and_clips_range(tmp_path):
    img = np.array([[[np.nan, np.inf, -1.0], [0.0, 0.5, 10.0], [-1.0, 0.0, 0.0]]], dtype=np.float32)
    out = tonemap(img)
    assert out.dtype == np.uint8
    assert out[0, 0].tolist() == [255, 0, 255]  # non-finite: magenta, never hidden as black
    assert out[0, 1, 0] == 0 and out[0, 1, 2] == 255 and out[0, 2].tolist() == [0, 0, 0]
    write_png(tmp_path / "p.png", img)
    assert (tmp_path / "p.png").stat().st_size > 0


def test_aces_rolls_highlights_off_and_is_monotone():
    x = np.linspace(0, 20, 401, dtype=np.float32)
    img = np.stack([x, x, x], -1)[None]
    aces = tonemap(img, 1.0, "aces")[0, :, 0].astype(int)
    clip = tonemap(img, 1.0, "clip")[0, :, 0].astype(int)
    assert (np.diff(aces) >= 0).all()
    assert aces[x.searchsorted(2.0)] < 255 and clip[x.searchsorted(2.0)] == 255  # no hard clip at 1
    assert aces[-1] == 255
    with pytest.raises(ValueError, match="tonemap"):
        tonemap(img, 1.0, "reinhard")


@pytest.mark.parametrize("curve, display", [("clip", 1.0), ("aces", 0.95)])
def test_auto_exposure_maps_the_995th_percentile(curve, display):
    from nrc.io.png import auto_exposure

    rng = np.random.default_rng(0)
    img = rng.exponential(0.3, size=(60, 80, 3)).astype(np.float32)
    img[0, 0] = np.nan  # ignored
    k = auto_exposure(img, curve)
    p = np.percentile(np.nan_to_num(img).max(-1), 99.5)
    x = k * p
    shown = x if curve == "clip" else x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    assert shown == pytest.approx(display, rel=0.02)
    out = tonemap(img, k, curve)
    assert (out == 255).any(-1).mean() <= 0.006  # about 0.5 % clip at most
    assert auto_exposure(np.zeros((4, 4, 3), np.float32)) == 1.0


@pytest.mark.parametrize("exposure", [-1.0, 0.0, float("nan"), float("inf"), "bright", True])
def test_display_settings_reject_bad_exposure(exposure):
    from nrc.errors import ConfigError
    from nrc.io.png import DisplaySettings

    with pytest.raises(ConfigError, match="exposure"):
        DisplaySettings.from_config({"exposure": exposure})
    with pytest.raises(ConfigError, match="tonemap"):
        DisplaySettings.from_config({"tonemap": "filmic"})
    assert DisplaySettings.from_config({"exposure": "auto"}).exposure is None
    assert DisplaySettings.from_config({"exposure": 2, "tonemap": "clip"}) == DisplaySettings("clip", 2.0)
