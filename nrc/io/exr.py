"""Linear float32 RGB images as OpenEXR files (via the ``OpenEXR`` >= 3.3 Python bindings).

Images are ``(H, W, 3)`` float32 arrays, row 0 at the top. Extra header attributes (strings, ints,
floats) round-trip, e.g. the sample count and config hash of a reference render.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from nrc.errors import NRCError

_STANDARD_KEYS = {
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "type", "version", "chunkCount", "tiles",
}


def write_exr(path: str | Path, rgb: np.ndarray, attributes: dict[str, Any] | None = None,
              alpha: np.ndarray | None = None) -> None:
    """Write an ``(H, W, 3)`` float32 linear RGB image (ZIP compression) with optional header attributes and
    an optional ``(H, W)`` alpha channel ``A``."""
    rgb = np.ascontiguousarray(np.asarray(rgb, dtype=np.float32))
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_exr expects an (H, W, 3) image, got shape {rgb.shape}")
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    channels = {"RGB": rgb}
    if alpha is not None:
        alpha = np.asarray(alpha, dtype=np.float32)
        if alpha.shape != rgb.shape[:2]:
            raise ValueError(f"write_exr: alpha must be {rgb.shape[:2]}, got {alpha.shape}")
        channels = {"RGBA": np.ascontiguousarray(np.concatenate([rgb, alpha[..., None]], axis=-1))}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def read_exr(path: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """Read an RGB(A) EXR; returns the ``(H, W, 3)`` float32 image and its non-standard header attributes."""
    path = Path(path)
    if not path.is_file():
        raise NRCError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = f.channels()
            header = dict(f.header())
            names = set(ch)
            if {"R", "G", "B"} <= names:
                rgb = np.stack([ch[c].pixels for c in "RGB"], axis=-1)
            elif "Y" in names:
                rgb = np.repeat(ch["Y"].pixels[..., None], 3, axis=-1)
            else:
                raise NRCError(f"{path}: no R, G, B (or Y) channels, found {sorted(names)}")
    except NRCError:
        raise
    except Exception as exc:  # the bindings raise plain RuntimeError/OSError on malformed files
        raise NRCError(f"{path}: not a readable EXR file ({exc})") from None
    attrs = {k: v for k, v in header.items() if k not in _STANDARD_KEYS}
    return rgb.astype(np.float32), attrs
