"""Ratio tracking (Novák, Selle, Jarosz 2014) with a global or per-brick majorant and Russian roulette.

``T = prod_i (1 - sigma_t(x_i) / m)`` over the tentative collisions ``x_i`` of a majorant process of rate ``m``
on the segment. Bounded in ``[0, 1]`` because the majorant is checked to bound ``sigma_t``. A Russian roulette
on the running weight keeps dense rays cheap and stays unbiased: when it drops below ``roulette_threshold``
the ray survives with probability equal to the weight and continues with weight 1 (else it returns 0).
"""

from __future__ import annotations

import torch
from torch import Tensor

from nrc.transport.tracking import DEFAULT_MODE, RATIO, TrackingStats, clip_segments, track


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
    roulette_threshold: float = 0.1,
    return_stats: bool = False,
) -> Tensor | tuple[Tensor, TrackingStats]:
    """Ratio-tracking transmittance of the segments ``[t0, t1]`` (clipped to the box) of the rays.

    Args:
        majorant: ``"brick"`` (per-brick majorants via the vectorised DDA) or ``"global"``.
        roulette_threshold: roulette on the running weight below this value (0 disables).
        return_stats: also return the :class:`~nrc.transport.tracking.TrackingStats`.

    Returns:
        ``T`` ``(N,)`` float32 in ``[0, 1]`` (unbiased; ``1`` for rays that miss the box).
    """
    direction = direction.to(torch.float32)
    o, a, b = clip_segments(grid, origin, direction, t0, t1)
    st = TrackingStats()
    T = track(grid, majorants, o, direction, a, b, gen, RATIO, majorant,
              roulette_threshold=roulette_threshold, stats=st)
    return (T, st) if return_stats else T
