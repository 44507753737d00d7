"""Tone-mapped PNG previews of linear images (display only: EXR files keep the linear data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def tonemap(rgb: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB -> 8-bit sRGB: exposure scale, clamp to [0, 1], sRGB transfer curve. NaN/Inf map to 0."""
    x = np.nan_to_num(np.asarray(rgb, dtype=np.float32) * exposure, nan=0.0, posinf=0.0, neginf=0.0)
    x = np.clip(x, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path: str | Path, rgb: np.ndarray, exposure: float = 1.0) -> None:
    """Write an ``(H, W, 3)`` linear image as a tone-mapped 8-bit PNG preview."""
    Image.fromarray(tonemap(rgb, exposure)).save(str(path))
