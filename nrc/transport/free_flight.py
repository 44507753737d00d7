"""One delta-tracking step of a wavefront of paths, against the brick majorants of a DDA traversal.

Used by the wavefront renderers (``pt`` and ``nrc``): every path in flight advances by one step per
iteration — either a tentative collision inside its current brick (real with probability
``sigma_t / majorant``, otherwise null and tracking goes on from there) or a move to the brick's exit, where
tracking restarts memorylessly against the next brick's majorant.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nrc.transport.tracking import MAJORANT_ATOL, MAJORANT_RTOL, MajorantError
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import BrickTraversal


@dataclass
class TrackingStep:
    """Result of :func:`delta_tracking_step` for ``N`` paths.

    Attributes:
        x: ``(N, 3)`` the point reached (tentative collision or brick exit), world units.
        real: ``(N,)`` bool, a real collision at ``x``.
        escaped: ``(N,)`` bool, the path left its segment (the box, or its light distance) without one.
        t: ``(N,)`` the paths' new ray parameter (unchanged at a real collision).
    """

    x: Tensor
    real: Tensor
    escaped: Tensor
    t: Tensor


def delta_tracking_step(grid: DensityGrid, trav: BrickTraversal, global_majorant: float, origin: Tensor,
                        direction: Tensor, t: Tensor, u: Tensor) -> TrackingStep:
    """Advance every path by one delta-tracking step; ``trav`` moves to the next brick where a path crossed.

    Args:
        grid: the medium.
        trav: the paths' brick traversal (majorant of the current brick, its exit, the segment end).
        global_majorant: the largest majorant (scales the absolute tolerance of the majorant check).
        origin, direction: ``(N, 3)`` the paths' rays; ``t``: ``(N,)`` their current ray parameter.
        u: ``(N, 2)`` uniforms: the free-flight distance and the real/null decision.

    Raises:
        MajorantError: a density lookup exceeded its brick's majorant (beyond rounding at brick faces):
            the majorant grid is stale or wrong. The check never clamps silently.
    """
    m_b = trav.majorant()
    t_exit = trav.t_exit()
    step = -torch.log1p(-u[:, 0]) / m_b.clamp(min=1e-30)
    t_cand = torch.where(m_b > 0, t + step, torch.full_like(step, float("inf")))
    cross = t_cand >= t_exit
    escaped = (cross & (t_exit >= trav.t_end)) | ~trav.active
    x = origin + torch.where(cross, t_exit, t_cand)[:, None] * direction
    sigma = grid.sigma_t(x)
    # Bounds are tight, so points rounded onto a neighbouring brick may exceed them by a hair: the same
    # tolerance as every other majorant check (nrc.transport.tracking).
    limit = m_b * (1.0 + MAJORANT_RTOL) + MAJORANT_ATOL * global_majorant
    if bool(((sigma > limit) & ~cross).any()):
        raise MajorantError("sigma_t exceeded the free-flight majorant: the majorant grid is stale or wrong")
    real = ~cross & (u[:, 1] * m_b < sigma)
    t_new = torch.where(cross, t_exit, torch.where(real, t, t_cand))
    trav.advance(cross & ~escaped)
    return TrackingStep(x=x, real=real, escaped=escaped, t=t_new)
