"""Brick majorant grid and its batched ray traversal (3-D DDA) for empty-space skipping.

Bricks live on the lattice of cell *centres* (the lattice trilinear interpolation works on): in continuous
cell coordinates ``u`` (cell ``i`` spans ``[i, i + 1]``, its centre is ``i + 0.5``) brick ``b`` spans
``u in [0.5 + (b - 1) B, 0.5 + b B]`` along each axis, so brick 0 also holds the half-cell clamp zone at
the low face and the last brick the one at the high face (the outer bricks extend past the box; rays are
clipped to the box first). A trilinear lookup inside brick ``b`` only blends the ``B + 1`` centres
``(b - 1) B .. b B`` (clamped to the grid), so the per-brick maximum and minimum of ``sigma_t =
density_scale * D`` over exactly those centres bound every lookup in the brick without dilation:
``minorant[b] <= sigma_t(x) <= majorant[b]``. Being exact for ``B = 1`` (one interpolation cell per brick),
the bounds stay tight near dense voxels, where a cell-aligned brick would have to be dilated.

``brick = 0`` makes a single brick covering the whole box with the global maximum and minimum (the
"global majorant" of delta tracking, through the same traversal code).

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
    """Per-brick max (or min) of ``sigma`` over the centres ``(b - 1) B .. b B`` of each brick (clamped)."""
    n = sigma.shape
    nb = [math.ceil((s - 0.5) / brick) + 1 for s in n]
    back = [nb[a] * brick + 1 - brick - n[a] for a in range(3)]
    x = F.pad(sigma[None, None], (brick, back[2], brick, back[1], brick, back[0]), mode="replicate")
    if not reduce_max:
        x = -x
    out = F.max_pool3d(x, kernel_size=brick + 1, stride=brick)[0, 0]
    return out if reduce_max else -out


class MajorantGrid:
    """Per-brick bounds of ``sigma_t`` for a density grid.

    Attributes:
        brick: bricks are ``brick`` cells wide along each axis (0: one brick for the whole box).
        brick_size: brick edge length in world units.
        origin: ``(3,)`` world position of the low corner of brick ``(0, 0, 0)``.
        majorant: ``(bx, by, bz)`` per-brick maximum of ``sigma_t``.
        minorant: ``(bx, by, bz)`` per-brick minimum of ``sigma_t``.
        global_majorant: maximum of ``sigma_t`` over the whole grid (a float).
    """

    def __init__(self, grid: DensityGrid, brick: int = 8) -> None:
        if brick < 0:
            raise ValueError(f"brick size must be >= 0, got {brick}")
        self.grid = grid
        self.brick = int(brick)
        sigma = grid.density * grid.density_scale
        if self.brick == 0:
            self.brick_size = float(grid.box.extent.max())
            self.origin = grid.box.lo.clone()
            self.majorant = sigma.max().reshape(1, 1, 1)
            self.minorant = sigma.min().reshape(1, 1, 1)
        else:
            self.brick_size = grid.voxel_size * self.brick
            self.origin = grid.box.lo + (0.5 - self.brick) * grid.voxel_size
            self.majorant = _brick_reduce(sigma, self.brick, True).contiguous()
            self.minorant = _brick_reduce(sigma, self.brick, False).contiguous()
        self.global_majorant = float(sigma.max())
        self.shape = tuple(self.majorant.shape)

    @staticmethod
    def auto_brick(grid: DensityGrid, max_steps: float = 16.0, largest: int = 16) -> int:
        """The largest power-of-two brick (<= ``largest``) whose crossing at the global majorant costs at
        most ``max_steps`` tentative collisions: ``global_majorant * brick * voxel_size <= max_steps``.
        Thin media get coarse bricks (cheap traversal); very dense ones get single-cell bricks, whose tight
        bounds keep delta tracking from stepping through empty space at the dense rate."""
        rate = grid.density_scale * grid.max_density * grid.voxel_size
        brick = largest
        while brick > 1 and rate * brick > max_steps:
            brick //= 2
        return brick

    def brick_of(self, x: Tensor) -> Tensor:
        """Integer brick coordinates ``(N, 3)`` of world points, clamped into the brick grid."""
        b = ((x - self.origin) / self.brick_size).floor().long()
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
        self.t_end = t_far.clone()
        self.active = t_far > t_near
        entry = origin + t_near[:, None] * direction
        mid = origin + (0.5 * (t_near + t_far))[:, None] * direction
        # Entry points on a brick face may round to either side: take the brick of a point a hair inside.
        nudge = torch.minimum(t_far - t_near, torch.full_like(t_near, 1e-4 * grid.brick_size))
        inside = torch.where(self.active[:, None], entry + nudge[:, None] * direction, mid)
        self.cell = grid.brick_of(inside)
        self.step = torch.sign(direction).long()
        size = grid.brick_size
        boundary = grid.origin + (self.cell + (self.step > 0).long()).to(origin.dtype) * size
        safe = torch.where(direction == 0, torch.ones_like(direction), direction)
        inf = torch.full_like(direction, float("inf"))
        self.t_next = torch.where(direction == 0, inf, (boundary - origin) / safe)
        self.t_next = torch.maximum(self.t_next, self.t[:, None])
        self.t_delta = torch.where(direction == 0, inf, size / safe.abs())
        self._hi = torch.tensor(grid.shape, device=origin.device) - 1

    _STATE = ("t", "t_end", "active", "cell", "step", "t_next", "t_delta")

    def restart(self, idx: Tensor, origin: Tensor, direction: Tensor, t_near: Tensor, t_far: Tensor) -> None:
        """Replace the rays at indices ``idx`` by new rays (as if freshly constructed)."""
        fresh = BrickTraversal(self.grid, origin, direction, t_near, t_far)
        for name in self._STATE:
            getattr(self, name)[idx] = getattr(fresh, name)

    def select(self, keep: Tensor) -> None:
        """Keep only the rays selected by ``keep`` (a boolean mask or an index tensor), in order."""
        for name in self._STATE:
            setattr(self, name, getattr(self, name)[keep])

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

    def skip_empty(self, min_rays: int = 1) -> int:
        """Move every active ray out of empty bricks (majorant 0) in one call; returns the bricks skipped.

        Each ray advances until it reaches a brick with a positive majorant or leaves its segment
        (then it is inactive). Equivalent to calling :meth:`advance` while the brick is empty, but
        only the rays in empty bricks are touched and no tracking step is spent on them. Does nothing
        when fewer than ``min_rays`` rays sit in empty bricks (the loop's fixed cost would not pay).
        """
        idx = (self.active & (self.majorant() == 0)).nonzero().squeeze(1)
        if len(idx) < max(min_rays, 1):
            return 0
        sub = object.__new__(BrickTraversal)
        sub.grid, sub._hi = self.grid, self._hi
        for name in self._STATE:
            setattr(sub, name, getattr(self, name)[idx])
        skipped = 0
        empty = sub.active
        while True:
            n = int(empty.sum())
            if n == 0:
                break
            skipped += n
            sub.advance(empty)
            empty = sub.active & (sub.majorant() == 0)
        for name in self._STATE:
            getattr(self, name)[idx] = getattr(sub, name)
        return skipped

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


class BrickTables:
    """Majorant grids in the form a per-slot step consumes: one flat table of brick majorants and, per grid, a
    few scalars (``values``), so that a compiled step takes both as *inputs* (one graph for every scene).

    Table 0 serves free flights and table 1 shadow rays (one table when both use the same grid). A step finds
    a ray's brick from its current point, nudged ``1e-4`` brick edges along the ray (a point on a face
    belongs to the brick it enters), and the distance to that brick's exit (:meth:`segment`). No traversal
    state is carried between steps (unlike :class:`BrickTraversal`), so refills, shadow rays and compaction
    need no bookkeeping.

    Args:
        free_flight, shadow: the :class:`MajorantGrid` of each kind of ray.
    """

    PER_TABLE = 11  # origin (3), last brick index (3), flat stride (3), brick edge, offset into flat

    def __init__(self, free_flight: MajorantGrid, shadow: MajorantGrid) -> None:
        grids = [free_flight] if shadow is free_flight else [free_flight, shadow]
        self.n_tables = len(grids)
        self.flat = torch.cat([g.majorant.reshape(-1) for g in grids]).float().contiguous()
        self.values: list[float] = []
        offset = 0
        for g in grids:
            self.values += [float(v) for v in g.origin.tolist()]
            self.values += [float(n - 1) for n in g.shape]
            self.values += [float(g.shape[1] * g.shape[2]), float(g.shape[2]), 1.0, float(g.brick_size), float(offset)]
            offset += g.majorant.numel()

    @staticmethod
    def segment(flat: Tensor, values: list, n_tables: int, o: tuple, d: tuple, t: Tensor,
                shadow: Tensor) -> tuple[Tensor, Tensor]:
        """``(majorant, t_exit)`` ``(S,)`` of the brick each ray ``o + t d`` (component form) is in at ``t``;
        ``shadow`` picks table 1 per slot when there are two. ``values`` are :attr:`values` as numbers or
        0-d tensors. ``t_exit > t`` always (a ray on a face moves on by the nudge)."""
        k = BrickTables.PER_TABLE
        tables = [values[i * k:(i + 1) * k] for i in range(n_tables)]

        def per_slot(j: int) -> Tensor:
            v0 = tables[0][j] + torch.zeros_like(t)
            if n_tables == 1:
                return v0
            return torch.where(shadow, tables[1][j] + torch.zeros_like(t), v0)

        size = per_slot(9)
        tn = t + size * 1e-4
        idx = per_slot(10).long()
        t_exit = None
        for a in range(3):
            org = per_slot(a)
            c = ((o[a] + tn * d[a] - org) / size).floor().nan_to_num(0.0, 0.0, 0.0).clamp(min=0.0)
            c = torch.minimum(c, per_slot(3 + a))
            bound = org + (c + (d[a] > 0).to(c.dtype)) * size
            tb = torch.where(d[a] != 0, (bound - o[a]) / d[a], torch.full_like(t, math.inf))
            t_exit = tb if t_exit is None else torch.minimum(t_exit, tb)
            idx = idx + c.long() * per_slot(6 + a).long()
        return flat[idx], torch.maximum(t_exit, tn)
