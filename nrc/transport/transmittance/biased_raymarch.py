"""Biased ray marching: the Kettunen comb alone, ``T = exp(-X)`` (order 0 of the unbiased estimator).

``X = h * sum_{j<M} sigma_t(a + (u + j) h)`` with one uniform offset ``u`` and ``h = L / M`` is unbiased for the
optical depth, so ``exp(-X)`` is biased upwards (Jensen); the bias shrinks as ``M`` grows. ``M`` is fixed
(``m``), set by a step length (``step``: ``M = ceil(L / step)``), or by default taken from the control optical
thickness exactly as in the unbiased estimator. Exact for constant density; always in ``[0, 1]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from nrc.transport.tracking import TrackingStats, clip_segments, optical_depth_bounds
from nrc.transport.transmittance.unbiased_raymarch import OPAQUE_TAU, combs, tuple_size


def estimate(
    grid,
    majorants,
    origin: Tensor,
    direction: Tensor,
    t0: float | Tensor | None,
    t1: float | Tensor | None,
    gen: torch.Generator,
    *,
    m: int | None = None,
    step: float | None = None,
    max_m: int = 1024,
    chunk_lookups: int = 1 << 20,
    return_stats: bool = False,
) -> Tensor | tuple[Tensor, TrackingStats]:
    """Biased ray-marching transmittance of the segments ``[t0, t1]`` (clipped to the box).

    Args:
        m: samples per ray (takes precedence over ``step``).
        step: world-unit step; ``M = ceil(L / step)`` per ray.
        max_m: cap on ``M`` (all three ways).
        chunk_lookups: lookups evaluated per ``sigma_t`` call.

    Returns:
        ``T`` ``(N,)`` float32 in ``[0, 1]``.
    """
    if m is not None and int(m) < 1:
        raise ValueError(f"biased_raymarch: m must be >= 1, got {m}")
    if step is not None and not float(step) > 0:
        raise ValueError(f"biased_raymarch: step must be > 0, got {step}")
    direction = direction.to(torch.float32)
    o, a, b = clip_segments(grid, origin, direction, t0, t1)
    T = torch.ones_like(a)
    st = TrackingStats()
    todo = torch.nonzero(b > a).squeeze(1)
    st.rays = int(todo.numel())
    if st.rays and majorants.global_majorant > 0:
        o, d, a, b = o[todo], direction[todo], a[todo], b[todo]
        tau_major, tau_minor = optical_depth_bounds(majorants, o, d, a, b)
        if m is not None:
            mm = torch.full_like(a, int(m), dtype=torch.long).clamp(max=max_m)
        elif step is not None:
            mm = torch.ceil((b - a).to(torch.float64) / float(step)).clamp(min=1, max=max_m).long()
        else:
            mm = tuple_size(tau_major - tau_minor, max_m)
        opaque = tau_minor > OPAQUE_TAU
        march = (tau_major > 0) & ~opaque
        Tt = torch.where(opaque, torch.zeros_like(a), torch.ones_like(a))
        sel = torch.nonzero(march).squeeze(1)
        if sel.numel():
            X = combs(grid, o[sel], d[sel], a[sel], b[sel], mm[sel], torch.ones_like(mm[sel]), gen, chunk_lookups)
            Tt[sel] = torch.exp(-X[:, 0])
            st.lookups = st.collisions = int(mm[sel].sum())
            st.iterations = 1
        T[todo] = Tt
    return (T, st) if return_stats else T
