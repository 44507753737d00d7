"""Brick majorant grid and its batched ray traversal (3-D DDA) for empty-space skipping.

The density box is split into bricks of ``brick`` x ``brick`` x ``brick`` cells (the last brick along an
axis may extend past the box; rays are clipped to the box first). For each brick the grid stores the
maximum and minimum of ``sigma_t = density_scale * D`` over every cell whose value can enter a trilinear
lookup inside the brick: the brick's own cells dilated by one cell on every side. Hence for any point
``x`` in brick ``b``: ``minorant[b] <= sigma_t(x) <= majorant[b]``.

The grid is built from a :class:`~nrc.volume.grid.DensityGrid` and is tied to its ``density_scale``:
build a new one when the scale changes.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from nrc.volume.grid import DensityGrid


def _brick_reduce(sigma: Tensor, brick: int, reduce_max: bool) -> Tensor:
    """Per-brick max (or min) of ``sigma`` over each brick dilated by one cell (edge cells replicated)."""
    n = sigma.shape
    nb = [math.ceil(s / brick) for s in n]
    x = sigma[None, None]
    x = F.pad(x, (1, 1, 1, 1, 1, 1), mode="replicate")
    extra = [nb[a] * brick + 2 - (n[a] + 2) for a in range(3)]
    x = F.pad(x, (0, extra[2], 0, extra[1], 0, extra[0]), mode="replicate")
    if not reduce_max:
        x = -x
    out = F.max_pool3d(x, kernel_size=brick + 2, stride=brick)[0, 0]
    return out if reduce_max else -out


class MajorantGrid:
    """Per-brick bounds of ``sigma_t`` for a density grid.

    Attributes:
        brick: bricks are ``brick`` cells wide along each axis.
        brick_size: brick edge length in world units.
        majorant: ``(bx, by, bz)`` per-brick maximum of ``sigma_t`` (dilated by one cell).
        minorant: ``(bx, by, bz)`` per-brick minimum of ``sigma_t`` (dilated by one cell).
        global_majorant: maximum of ``sigma_t`` over the whole grid (a float).
    """

    def __init__(self, grid: DensityGrid, brick: int = 8) -> None:
        if brick < 1:
            raise ValueError(f"brick size must be >= 1, got {brick}")
        self.grid = grid
        self.brick = int(brick)
        self.brick_size = grid.voxel_size * self.brick
        sigma = grid.density * grid.density_scale
        self.majorant = _brick_reduce(sigma, self.brick, True).contiguous()
        self.minorant = _brick_reduce(sigma, self.brick, False).contiguous()
        self.global_majorant = float(sigma.max())
        self.shape = tuple(self.majorant.shape)

    def brick_of(self, x: Tensor) -> Tensor:
        """Integer brick coordinates ``(N, 3)`` of world points, clamped into the brick grid."""
        b = ((x - self.grid.box.lo) / self.brick_size).floor().long()
        hi = torch.tensor(self.shape, device=x.device) - 1
        return torch.minimum(b.clamp(min=0), hi)

    def majorant_at(self, x: Tensor) -> Tensor:
        """Brick majorant ``(N,)`` at world points ``(N, 3)`` (points outside the box use the nearest brick)."""
        b = self.brick_of(x)
        return self.majorant[b[:, 0], b[:, 1], b[:, 2]]

    def traverse(self, origin: Tensor, direction: Tensor, t_near: Tensor, t_far: Tensor) -> BrickTraversal:
        """Start a batched DDA over the bricks pierced by the segments ``[t_near, t_far]`` of the rays."""
        return BrickTraversal(self, origin, direction, t_near, t_far)

    def integrate_bounds(
        self, origin: Tensor, direction: Tensor, t_near: Tensor, t_far: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Integrals of the brick majorant and minorant along ray segments.

        Returns ``(tau_major, tau_minor)``, each ``(N,)``: upper and lower bounds of the optical depth
        of ``[t_near, t_far]``. Loops over DDA steps (at most ``bx + by + bz`` of them), never over rays.
        """
        trav = self.traverse(origin, direction, t_near, t_far)
        tau_major = torch.zeros_like(t_near)
        tau_minor = torch.zeros_like(t_near)
        while bool(trav.active.any()):
            t0, t1 = trav.t, trav.t_exit()
            length = torch.where(trav.active, t1 - t0, torch.zeros_like(t0))
            tau_major = tau_major + length * trav.majorant()
            tau_minor = tau_minor + length * trav.minorant()
            trav.advance(trav.active)
        return tau_major, tau_minor


class BrickTraversal:
    """State of a batched 3-D DDA over a :class:`MajorantGrid` (Amanatides & Woo).

    Each ray walks the bricks that its segment ``[t_near, t_far]`` pierces, in order. ``t`` is the start
    of the current brick segment and :meth:`t_exit` its end. :meth:`advance` moves the selected rays to
    their next brick; a ray becomes inactive once its segment is used up. Rays whose segment is empty
    (``t_near >= t_far``) start inactive.

    Args:
        grid: the majorant grid.
        origin, direction: ``(N, 3)`` rays (direction need not be unit; ``t`` is in units of it).
        t_near, t_far: ``(N,)`` segment, already clipped to the grid box.
    """

    def __init__(self, grid: MajorantGrid, origin: Tensor, direction: Tensor, t_near: Tensor, t_far: Tensor) -> None:
        self.grid = grid
        self.t = t_near.clone()
        self.t_end = t_far
        self.active = t_far > t_near
        entry = origin + t_near[:, None] * direction
        mid = origin + (0.5 * (t_near + t_far))[:, None] * direction
        # Entry points on a brick face may round to either side: take the brick of a point a hair inside.
        nudge = torch.minimum(t_far - t_near, torch.full_like(t_near, 1e-4 * grid.brick_size))
        inside = torch.where(self.active[:, None], entry + nudge[:, None] * direction, mid)
        self.cell = grid.brick_of(inside)
        self.step = torch.sign(direction).long()
        size = grid.brick_size
        lo = grid.grid.box.lo
        boundary = lo + (self.cell + (self.step > 0).long()).to(origin.dtype) * size
        safe = torch.where(direction == 0, torch.ones_like(direction), direction)
        inf = torch.full_like(direction, float("inf"))
        self.t_next = torch.where(direction == 0, inf, (boundary - origin) / safe)
        self.t_next = torch.maximum(self.t_next, self.t[:, None])
        self.t_delta = torch.where(direction == 0, inf, size / safe.abs())
        self._hi = torch.tensor(grid.shape, device=origin.device) - 1

    def majorant(self) -> Tensor:
        """Majorant ``(N,)`` of each ray's current brick."""
        c = self.cell
        return self.grid.majorant[c[:, 0], c[:, 1], c[:, 2]]

    def minorant(self) -> Tensor:
        """Minorant ``(N,)`` of each ray's current brick."""
        c = self.cell
        return self.grid.minorant[c[:, 0], c[:, 1], c[:, 2]]

    def t_exit(self) -> Tensor:
        """End ``(N,)`` of each ray's current brick segment (never beyond ``t_far``)."""
        return torch.minimum(self.t_next.amin(dim=-1), self.t_end)

    def advance(self, mask: Tensor) -> None:
        """Move the rays selected by the boolean ``(N,)`` mask to their next brick."""
        mask = mask & self.active
        t_exit = self.t_exit()
        axis = self.t_next.argmin(dim=-1, keepdim=True)
        onehot = torch.zeros_like(self.cell).scatter_(1, axis, 1) * mask[:, None].long()
        self.cell = self.cell + onehot * self.step
        self.t_next = torch.where(onehot.bool(), self.t_next + self.t_delta, self.t_next)
        self.t = torch.where(mask, t_exit, self.t)
        out = ((self.cell < 0) | (self.cell > self._hi)).any(dim=-1)
        self.active = self.active & ~(mask & ((self.t >= self.t_end) | out))
        self.cell = torch.minimum(self.cell.clamp(min=0), self._hi)
