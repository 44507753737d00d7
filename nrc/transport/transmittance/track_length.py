"""Track-length transmittance: delta tracking as a binary estimator.

``T = 1`` if the free flight sampled by delta tracking passes the end of the segment without a real
collision, else ``0``. Unbiased but high variance (``T (1 - T)``); use it for free-flight sampling, not for
shadow rays.
"""

from __future__ import annotations

import torch
from torch import Tensor

from nrc.transport.tracking import DEFAULT_MODE, DELTA, TrackingStats, clip_segments, track


def estimate(
    grid,
    majorants,
    origin: Tensor,
    direction: Tensor,
    t0: float | Tensor | None,
    t1: float | Tensor | None,
    gen: torch.Generator,
    *,
    majorant: str = DEFAULT_MODE,
    return_stats: bool = False,
) -> Tensor | tuple[Tensor, TrackingStats]:
    """Track-length (binary) transmittance of the segments ``[t0, t1]`` (clipped to the box).

    Returns:
        ``T`` ``(N,)`` float32, each 0 or 1.
    """
    direction = direction.to(torch.float32)
    o, a, b = clip_segments(grid, origin, direction, t0, t1)
    st = TrackingStats()
    _, hit = track(grid, majorants, o, direction, a, b, gen, DELTA, majorant, stats=st)
    T = (~hit).to(torch.float32)
    return (T, st) if return_stats else T
