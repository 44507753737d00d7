"""Denoising a rendered image with Intel Open Image Denoise (``pyoidn``; ``pip install -e '.[denoise]'``).

``denoise: none | oidn`` (root config key) applies to every renderer: the run directory keeps the raw
``image.exr`` and adds ``image_denoised.exr`` and ``preview_denoised.png`` (at the raw preview's exposure, so
the two compare); ``metrics.json`` records ``time_denoise_s``. The filter is OIDN's ``RT`` filter for HDR
colour (no albedo or normal buffers: a participating medium has no surface to give them). OIDN needs finite,
non-negative input, so only its copy is cleaned (NaN/Inf and negative values to 0); the raw image is
untouched, and :func:`clamp_bias` measures what the cleaning adds to the image mean (unbiased NRC,
``renderer.debias``, has negative pixels; ``metrics.json``: ``denoise_clamp_bias``). An accumulated NRC run
denoises its accumulated image. Deterministic for a given input on the same machine (OIDN's CPU device).
"""

from __future__ import annotations

import numpy as np

from nrc.errors import ConfigError, NRCError

DENOISERS = ("none", "oidn")


def denoiser_from_config(cfg) -> str:
    """The validated ``denoise`` key (``none`` when absent)."""
    value = cfg.get("denoise", "none") if hasattr(cfg, "get") else "none"
    if value not in DENOISERS:
        raise ConfigError(f"denoise must be one of {', '.join(DENOISERS)}, got {value!r}")
    if value == "oidn":
        _pyoidn()
    return value


def _pyoidn():
    try:
        import pyoidn
    except ImportError:
        raise NRCError("denoise=oidn (the default) needs Intel Open Image Denoise: pip install pyoidn (a "
                       "dependency of nrc), or run with denoise=none") from None
    return pyoidn


def oidn_version() -> str:
    """``pyoidn <version>``."""
    from importlib.metadata import version

    return f"pyoidn {version('pyoidn')}"


def _clean(rgb: np.ndarray) -> np.ndarray:
    """The denoiser's copy: NaN/Inf and negative values to 0, contiguous."""
    return np.ascontiguousarray(np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0))


def clamp_bias(rgb: np.ndarray) -> float:
    """The relative change of the image's mean that the denoiser's cleaning (negative and non-finite values to 0)
    makes: ``(mean(clean) - mean(finite raw)) / |mean(finite raw)|`` over all channels (0 for a clean image)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    raw = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    base = abs(raw.mean())
    return float((_clean(rgb).mean() - raw.mean()) / base) if base > 0 else 0.0


def denoise(rgb: np.ndarray, quality: str = "high") -> np.ndarray:
    """OIDN's HDR ``RT`` filter applied to a cleaned copy of the linear ``(H, W, 3)`` image; float32 result."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"denoise expects an (H, W, 3) image, got shape {rgb.shape}")
    clean = _clean(rgb)
    out = _pyoidn().denoise(clean, hdr=True, quality=quality)
    return np.asarray(out, dtype=np.float32)
