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


def test_tonemap_handles_nan_and_range(tmp_path):
    img = np.array([[[np.nan, np.inf, -1.0], [0.0, 0.5, 10.0]]], dtype=np.float32)
    out = tonemap(img)
    assert out.dtype == np.uint8
    assert out[0, 0].tolist() == [0, 0, 0] and out[0, 1, 0] == 0 and out[0, 1, 2] == 255
    write_png(tmp_path / "p.png", img)
    assert (tmp_path / "p.png").stat().st_size > 0
