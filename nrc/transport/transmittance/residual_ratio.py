"""Residual ratio tracking (Novák, Selle, Jarosz 2014) with per-brick controls.

On each brick piece of the segment the control extinction is ``sigma_c = (majorant + minorant) / 2`` and the
residual majorant ``m_r = (majorant - minorant) / 2 >= |sigma_t - sigma_c|``. The control optical depth
``tau_c`` is integrated exactly per piece and

    T = exp(-tau_c) * prod_i (1 - (sigma_t(x_i) - sigma_c(x_i)) / m_r(x_i))

over the tentative collisions of the residual-majorant process (bricks with ``m_r = 0`` take no steps and
contribute their exact transmittance). Zero variance where ``sigma_t == sigma_c``; each factor lies in
``[0, 2]``, so estimates can exceed 1. An optional Russian roulette on the running weight ``exp(-tau_c) prod``
(as in ratio tracking: below the threshold survive with probability equal to the weight and continue with 1)
bounds the work of dense rays.
"""

from __future__ import annotations

import torch
from torch import Tensor

from nrc.transport.tracking import RESIDUAL, TrackingStats, clip_segments, track


def estimate(
    grid,
    majorants,
    origin: Tensor,
    direction: Tensor,
    t0: float | Tensor | None,
    t1: float | Tensor | None,
    gen: torch.Generator,
    *,
    roulette_threshold: float = 0.0,
    return_stats: bool = False,
) -> Tensor | tuple[Tensor, TrackingStats]:
    """Residual-ratio-tracking transmittance of the segments ``[t0, t1]`` (clipped to the box).

    Args:
        roulette_threshold: roulette on the running weight below this value (0 disables).
        return_stats: also return the :class:`~nrc.transport.tracking.TrackingStats`.

    Returns:
        ``T`` ``(N,)`` float32, unbiased, ``>= 0`` (may exceed 1).
    """
    direction = direction.to(torch.float32)
    o, a, b = clip_segments(grid, origin, direction, t0, t1)
    st = TrackingStats()
    T = track(grid, majorants, o, direction, a, b, gen, RESIDUAL, "brick",
              roulette_threshold=roulette_threshold, stats=st)
    return (T, st) if return_stats else T
