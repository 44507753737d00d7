"""Error metrics of rendered images against a reference (linear RGB).

Conventions:

* Images are ``(H, W, 3)`` linear RGB, numpy arrays or torch tensors; sets of independent renders are
  ``(K, H, W, 3)`` (same scene, different seeds). Computation is in float64 numpy; every metric returns
  a Python ``float``.
* "Mean over pixels" averages a per-pixel, per-channel term over the selected pixels and the 3 channels.
* ``mask`` is an optional ``(H, W)`` bool array selecting the pixels to average over (``None``: all
  pixels); :func:`medium_mask` builds it from the reference's alpha (``1 -`` camera-ray transmittance).
* ``eps`` (default 0.01) keeps relative errors finite where the reference is black.

Recommended metrics are per-pixel statistics: :func:`mse`, :func:`rel_mse`, and, over K independent
renders, :func:`mean_relative_bias` / :func:`signed_relative_bias` (per-pixel expectation estimated over
renders) and :func:`relative_variance` (per-pixel variance across renders).

The ``thesis_*`` functions reproduce the definitions used by Spindler (2022) and Fedotov (2024) and are
NOT recommended: they compare image means (per-pixel errors of opposite sign cancel) and measure the
spatial variance of one image (image content, not noise). They exist only to compare with their tables.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

ArrayLike = np.ndarray | torch.Tensor


def _np(a: ArrayLike) -> np.ndarray:
    """``a`` as a float64 numpy array (torch tensors are detached and copied to the CPU)."""
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=np.float64)


def medium_mask(alpha_or_mask: ArrayLike, threshold: float = 1e-3) -> np.ndarray:
    """The ``(H, W)`` bool mask of pixels where the reference sees the medium.

    Args:
        alpha_or_mask: the reference's ``(H, W)`` alpha (``1 -`` transmittance of the camera ray), or an
            ``(H, W)`` bool mask, returned as is.
        threshold: pixels with ``alpha > threshold`` are selected.
    """
    if isinstance(alpha_or_mask, torch.Tensor):
        alpha_or_mask = alpha_or_mask.detach().cpu().numpy()
    a = np.asarray(alpha_or_mask)
    if a.ndim != 2:
        raise ValueError(f"medium_mask expects an (H, W) alpha or mask, got shape {a.shape}")
    return a.copy() if a.dtype == bool else a > threshold


def _select(term: np.ndarray, mask: ArrayLike | None) -> np.ndarray:
    """The ``(..., H, W, C)`` per-pixel ``term`` restricted to the masked pixels (``(..., N, C)``)."""
    if mask is None:
        return term
    m = medium_mask(mask)
    if m.shape != term.shape[-3:-1]:
        raise ValueError(f"mask shape {m.shape} does not match the image shape {term.shape[-3:-1]}")
    if not m.any():
        raise ValueError("mask selects no pixels")
    return term[..., m, :]


def _check_image(x: np.ndarray, ref: np.ndarray, name: str = "x") -> None:
    if ref.ndim != 3 or ref.shape[-1] != 3:
        raise ValueError(f"ref must be an (H, W, 3) image, got shape {ref.shape}")
    if x.shape[-3:] != ref.shape:
        raise ValueError(f"{name} has shape {x.shape}, expected (..., {', '.join(map(str, ref.shape))})")


def _renders(xs: ArrayLike, ref: ArrayLike, min_renders: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(xs, ref)`` as float64 arrays, checking ``xs`` is ``(K, H, W, 3)`` with ``K >= min_renders``."""
    xs, ref = _np(xs), _np(ref)
    _check_image(xs, ref, "xs")
    if xs.ndim != 4 or xs.shape[0] < min_renders:
        raise ValueError(f"xs must be (K, H, W, 3) with K >= {min_renders} independent renders, got {xs.shape}")
    return xs, ref


def _pair(x: ArrayLike, ref: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    x, ref = _np(x), _np(ref)
    _check_image(x, ref)
    if x.ndim != 3:
        raise ValueError(f"x must be an (H, W, 3) image, got shape {x.shape}")
    return x, ref


# ---------------------------------------------------------------------------- one image
def mse(x: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Mean squared error: mean over pixels of ``(x - r)^2``."""
    x, ref = _pair(x, ref)
    return float(_select((x - ref) ** 2, mask).mean())


def rel_mse(x: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None, eps: float = 0.01) -> float:
    """Relative MSE: mean over pixels of ``(x - r)^2 / (r^2 + eps)``."""
    x, ref = _pair(x, ref)
    return float(_select((x - ref) ** 2 / (ref**2 + eps), mask).mean())


_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def reference_scale(ref: ArrayLike, mask: ArrayLike | None = None) -> float:
    """The mean luminance of the reference over the selected pixels (all when ``mask`` is ``None``)."""
    ref = _np(ref)
    lum = ref @ _LUMINANCE
    sel = lum if mask is None else lum[medium_mask(mask)]
    return float(sel.mean())


def normalised_rel_mse(x: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None,
                       scale_mask: ArrayLike | None = None, eps: float = 0.01) -> float:
    """Relative MSE of ``x / s`` against ``ref / s``, ``s`` the reference's mean luminance over ``scale_mask``
    (the medium pixels; all pixels when ``None``), averaged over ``mask``.

    Plain :func:`rel_mse` adds ``eps = 0.01`` to ``r^2``, which dominates where the reference is ~0.1 and
    forgives a dark image (a uniformly 35 % too dark render of such a scene scores ~0.01); after normalising,
    the reference's medium pixels are ~1 and ``eps`` no longer decides the ranking.
    """
    s = reference_scale(ref, scale_mask)
    if not s > 0:
        raise ValueError("normalised_rel_mse: the reference is black over the scale pixels")
    x, ref = _pair(x, ref)
    return rel_mse(x / s, ref / s, mask, eps)


def mean_ratio(x: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None) -> float:
    """The image mean over the reference's over the selected pixels (1: no overall bias; < 1: too dark)."""
    x, ref = _pair(x, ref)
    return float(_select(x, mask).mean() / _select(ref, mask).mean())


def flicker(frames: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Temporal instability of a frame sequence ``(T, H, W, 3)`` (T >= 2) of a static camera: the mean over
    ``t = 1..T-1`` of the mean ``|I_t - I_{t-1}|`` over the selected pixels and channels, divided by the
    reference's mean over the same pixels. 0 for a still image; a renderer with independent Gaussian noise of
    standard deviation ``s`` per frame scores ``2 s / sqrt(pi)`` (about ``1.13 s``) over the reference's mean."""
    xs, ref = _renders(frames, ref, min_renders=2)
    scale = float(_select(ref, mask).mean())
    if not scale > 0:
        raise ValueError("flicker: the reference is black over the selected pixels")
    diffs = [float(_select(np.abs(xs[t] - xs[t - 1]), mask).mean()) for t in range(1, len(xs))]
    return float(np.mean(diffs)) / scale


def hdr_flip(x: ArrayLike, ref: ArrayLike) -> float:
    """Mean HDR-FLIP error (Andersson et al. 2021) of ``x`` against ``ref`` through NVIDIA's ``flip-evaluator``
    package (its defaults: 67 pixels per degree, ACES tone mapping, exposures chosen from the reference).
    Non-finite and negative values of the copies are set to 0 (FLIP needs non-negative input)."""
    try:
        import flip_evaluator
    except ImportError:
        raise ImportError("hdr_flip needs NVIDIA's FLIP: pip install -e '.[flip]' (flip-evaluator)") from None
    a, b = (np.ascontiguousarray(np.nan_to_num(_np(v), nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
                                 .astype(np.float32)) for v in (ref, x))
    _, mean, _ = flip_evaluator.evaluate(a, b, "HDR", applyMagma=False)
    return float(mean)


# ---------------------------------------------------------------------------- K independent renders
def signed_relative_bias(xs: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None, eps: float = 0.01) -> float:
    """Signed bias: mean over pixels of ``(mean_k x_k - r) / (|r| + eps)`` (> 0: too bright).

    The per-pixel expectation is estimated by the mean over the K independent renders ``xs``.
    """
    xs, ref = _renders(xs, ref)
    return float(_select((xs.mean(0) - ref) / (np.abs(ref) + eps), mask).mean())


def mean_relative_bias(xs: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None, eps: float = 0.01) -> float:
    """Mean relative bias: mean over pixels of ``|mean_k x_k - r| / (|r| + eps)``.

    Per-pixel errors do not cancel. The mean over K renders still carries noise of standard deviation
    ``sigma / sqrt(K)``, so an unbiased renderer scores about ``sqrt(2 / pi) sigma / (sqrt(K) (r + eps))``:
    use enough renders (or compare against that floor).
    """
    xs, ref = _renders(xs, ref)
    return float(_select(np.abs(xs.mean(0) - ref) / (np.abs(ref) + eps), mask).mean())


def relative_variance(xs: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None, eps: float = 0.01) -> float:
    """Relative variance: mean over pixels of ``var_k(x_k) / (r^2 + eps)``.

    ``var_k`` is the unbiased (``ddof=1``) variance of a pixel across the K >= 2 independent renders.
    """
    xs, ref = _renders(xs, ref, min_renders=2)
    return float(_select(xs.var(0, ddof=1) / (ref**2 + eps), mask).mean())


# ---------------------------------------------------------------------------- thesis definitions (not recommended)
def thesis_relative_bias(x: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Thesis "relative bias" (Spindler/Fedotov), NOT recommended: ``|mean(x) - mean(ref)| / mean(ref)``.

    A difference of image means: per-pixel errors of opposite sign cancel. Use :func:`mean_relative_bias`.
    """
    x, ref = _pair(x, ref)
    return float(abs(_select(x, mask).mean() - _select(ref, mask).mean()) / _select(ref, mask).mean())


def thesis_relative_variance(x: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Thesis "relative variance" (Spindler/Fedotov), NOT recommended: ``var(x) / mean(ref)``.

    ``var(x)`` is the spatial variance of the values of ONE image, so it measures image content as much as
    noise (and is not dimensionless). Use :func:`relative_variance` over independent renders.
    """
    x, ref = _pair(x, ref)
    return float(_select(x, mask).var() / _select(ref, mask).mean())


# ---------------------------------------------------------------------------- report
def _scope_report(xs: np.ndarray, ref: np.ndarray, mask: np.ndarray | None,
                  scale_mask: np.ndarray | None = None) -> dict[str, float | None]:
    """All metrics over one pixel set; single-image metrics are averaged over the renders."""
    per_render = {
        "mse": mse, "rel_mse": rel_mse, "thesis_relative_bias": thesis_relative_bias,
        "thesis_relative_variance": thesis_relative_variance, "mean_ratio": mean_ratio,
        "rel_mse_normalised": lambda x, r, m: normalised_rel_mse(x, r, m, scale_mask),
    }
    report: dict[str, float | None] = {k: float(np.mean([f(x, ref, mask) for x in xs])) for k, f in per_render.items()}
    report["mean_relative_bias"] = mean_relative_bias(xs, ref, mask)
    report["signed_relative_bias"] = signed_relative_bias(xs, ref, mask)
    report["relative_variance"] = relative_variance(xs, ref, mask) if len(xs) >= 2 else None
    return report


def error_report(xs: ArrayLike, ref: ArrayLike, mask: ArrayLike | None = None) -> dict[str, Any]:
    """Every metric, JSON-serialisable, over all pixels (``"all"``) and the medium pixels (``"medium"``).

    Args:
        xs: ``(K, H, W, 3)`` independent renders (an ``(H, W, 3)`` image counts as K = 1).
        ref: ``(H, W, 3)`` reference.
        mask: ``(H, W)`` bool mask or reference alpha (see :func:`medium_mask`); without it ``"medium"``
            is ``None``.

    Returns:
        ``{"renders": K, "all": {...}, "medium": {...} | None}``; each scope holds ``mse``, ``rel_mse``,
        ``rel_mse_normalised`` (images scaled so the reference's mean luminance over the medium pixels, or
        all pixels without a mask, is 1: :func:`normalised_rel_mse`), ``mean_ratio`` (image mean over the
        reference's) and the thesis metrics (averaged over the K renders), ``mean_relative_bias``,
        ``signed_relative_bias`` and ``relative_variance`` (``None`` when K = 1). Default ``eps`` = 0.01.
    """
    xs_np, ref_np = _np(xs), _np(ref)
    if xs_np.ndim == 3:
        xs_np = xs_np[None]
    xs_np, ref_np = _renders(xs_np, ref_np)
    m = None if mask is None else medium_mask(mask)
    return {
        "renders": int(len(xs_np)),
        "all": _scope_report(xs_np, ref_np, None, m),
        "medium": None if m is None else _scope_report(xs_np, ref_np, m, m),
    }
