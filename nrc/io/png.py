"""Tone-mapped 8-bit previews of linear images (display only: EXR files keep the linear data).

A preview is ``encode(curve(exposure * rgb))``: ``exposure`` a scale of the linear radiance, ``curve`` one of

* ``clip``: clamp to [0, 1];
* ``aces``: Narkowicz's fit of the ACES filmic curve, ``x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)``, which
  rolls highlights off (display 0.8 at x 0.98, 0.95 at 2.86) and reaches 1 only at x ~ 7.2;

and ``encode`` the sRGB transfer curve, rounded to 8 bits. ``exposure: auto`` picks the scale from the image
(:func:`auto_exposure`): the 99.5th percentile of the pixels' brightest channel maps to display 0.95 (``aces``) or 1
(``clip``), so at most about 0.5 % of the pixels clip. Figures that compare images use one exposure, taken
from the reference, for every panel: auto exposure per panel would brighten a dark (biased) image.
Non-finite pixels are shown magenta, never black: a preview does not hide NaN or Inf.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from nrc.errors import ConfigError

TONEMAPS = ("clip", "aces")
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
AUTO_PERCENTILE = 99.5
_AUTO_TARGET = {"clip": 1.0, "aces": 2.8633}  # curve input giving display 1 (clip) / 0.95 (aces)
_MAGENTA = np.array([255, 0, 255], dtype=np.uint8)


@dataclass(frozen=True)
class DisplaySettings:
    """How previews are tone mapped: the top-level ``tonemap`` and ``exposure`` keys of the config."""

    tonemap: str = "aces"
    """``clip`` or ``aces`` (module docstring)."""
    exposure: float | None = None
    """Linear scale before the curve; ``None`` (``exposure: auto``) picks it from the image."""

    @classmethod
    def from_config(cls, cfg: Any) -> DisplaySettings:
        curve = cfg.get("tonemap", "aces")
        if curve not in TONEMAPS:
            raise ConfigError(f"tonemap must be one of {', '.join(TONEMAPS)}, got {curve!r}")
        exposure = cfg.get("exposure", "auto")
        if exposure == "auto":
            return cls(curve, None)
        if isinstance(exposure, bool) or not isinstance(exposure, (int, float)) or not math.isfinite(exposure) \
                or exposure <= 0:
            raise ConfigError(f"exposure must be 'auto' or a positive finite number, got {exposure!r}")
        return cls(curve, float(exposure))

    def exposure_for(self, rgb: np.ndarray) -> float:
        """The fixed exposure, or :func:`auto_exposure` of ``rgb``."""
        return self.exposure if self.exposure is not None else auto_exposure(rgb, self.tonemap)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance ``(...,)`` of linear RGB ``(..., 3)``."""
    return np.asarray(rgb, dtype=np.float32) @ LUMINANCE


def auto_exposure(rgb: np.ndarray, curve: str = "aces") -> float:
    """The exposure that maps the 99.5th percentile of the finite pixels' brightest channel to display 0.95
    (``aces``) or 1 (``clip``); 1 for an image with no positive value."""
    rgb = np.asarray(rgb, dtype=np.float32)
    lum = rgb.max(axis=-1).reshape(-1)
    lum = lum[np.isfinite(lum)]
    if lum.size == 0:
        return 1.0
    p = float(np.percentile(lum, AUTO_PERCENTILE))
    return _AUTO_TARGET[curve] / p if p > 0 else 1.0


def tonemap(rgb: np.ndarray, exposure: float = 1.0, curve: str = "clip") -> np.ndarray:
    """Linear RGB ``(H, W, 3)`` -> 8-bit sRGB (module docstring); non-finite pixels become magenta."""
    if curve not in TONEMAPS:
        raise ValueError(f"tonemap must be one of {', '.join(TONEMAPS)}, got {curve!r}")
    rgb = np.asarray(rgb, dtype=np.float32)
    bad = ~np.isfinite(rgb).all(axis=-1)
    x = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0) * np.float32(exposure)
    if curve == "aces":
        x = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
    x = np.clip(x, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    out = np.round(srgb * 255.0).astype(np.uint8)
    out[bad] = _MAGENTA
    return out


def write_png(path: str | Path, rgb: np.ndarray, exposure: float = 1.0, curve: str = "clip") -> None:
    """Write an ``(H, W, 3)`` linear image as a tone-mapped 8-bit PNG preview."""
    Image.fromarray(tonemap(rgb, exposure, curve)).save(str(path))
