"""Brick majorant grid for empty-space skipping, its tables for the compiled transport step, and the one step of
the brick walk.

:func:`next_segment` is that step (pbrt-v4's majorant iterator in tensor form, stateless): the brick a ray is in
at its current point and where it leaves it. The compiled transport step calls it on every slot
(:meth:`BrickTables.segment`); the eager code's :class:`nrc.transport.tracking.MajorantWalk` loops over it.

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
import weakref
from collections.abc import Callable

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


MAX_SKIP = 16
_skip_cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def skip_radius(majorants: MajorantGrid, max_radius: int = MAX_SKIP) -> Tensor:
    """Empty-space radius per brick ``(bx, by, bz)`` (float32): ``r >= 1`` when every brick within L-inf
    distance ``r - 1`` has a zero majorant (bricks outside the grid count as empty), 0 for non-empty bricks;
    capped at ``max_radius``. A ray in a brick of radius ``r`` can cross the ``(2r-1)^3`` empty cube around it
    in one step. Cached per majorant grid (recomputed when its majorant tensor changes)."""
    key = (majorants.majorant.data_ptr(), majorants.majorant._version, int(max_radius))
    hit = _skip_cache.get(majorants)
    if hit is not None and hit[0] == key:
        return hit[1]
    covered = (majorants.majorant > 0).to(torch.float32)[None, None]
    r = torch.zeros(majorants.shape, dtype=torch.float32, device=covered.device)
    for k in range(1, int(max_radius) + 1):
        free = covered[0, 0] == 0
        if not bool(free.any()):
            break
        r = torch.where(free, torch.full_like(r, float(k)), r)
        covered = torch.nn.functional.max_pool3d(covered, 3, stride=1, padding=1)
    _skip_cache[majorants] = (key, r)
    return r


class BrickTables:
    """Majorant grids in the form a per-slot step consumes: one flat table of brick majorants, then the bricks'
    empty-space radii (:func:`skip_radius`), and, per grid, a few scalars (``values``), so that a compiled step
    takes both as *inputs* (one graph for every scene).

    Table 0 serves free flights and table 1 shadow rays (one table when both use the same grid). A step finds
    a ray's brick from its current point, nudged ``1e-4`` brick edges along the ray (a point on a face
    belongs to the brick it enters), and the distance to that brick's exit, or, in an empty brick, to the exit
    of the empty cube around it (:meth:`segment`: the eager walk's jump, so a camera ray crosses empty space in a
    few steps). No traversal state is carried between steps (:func:`next_segment`), so refills, shadow rays and
    compaction need no bookkeeping.

    Args:
        free_flight, shadow: the :class:`MajorantGrid` of each kind of ray.
    """

    PER_TABLE = 12  # origin (3), last brick index (3), flat stride (3), brick edge, offset into flat, radii offset

    def __init__(self, free_flight: MajorantGrid, shadow: MajorantGrid) -> None:
        grids = [free_flight] if shadow is free_flight else [free_flight, shadow]
        self.n_tables = len(grids)
        majorants = [g.majorant.reshape(-1).float() for g in grids]
        radii = [skip_radius(g).reshape(-1).float() for g in grids]
        self.flat = torch.cat(majorants + radii).contiguous()
        n_maj = sum(m.numel() for m in majorants)
        self.values: list[float] = []
        offset = 0
        for g in grids:
            self.values += self.grid_values(g, offset, n_maj)
            offset += g.majorant.numel()

    @staticmethod
    def grid_values(g: MajorantGrid, offset: int = 0, radii: int = 0) -> list[float]:
        """One grid's :data:`PER_TABLE` values: origin (3), last brick index (3), flat stride (3), brick edge,
        offset of its first brick in the flat table, and how far after a brick's majorant its radius lies (0: the
        table has no radii)."""
        return ([float(v) for v in g.origin.tolist()] + [float(n - 1) for n in g.shape]
                + [float(g.shape[1] * g.shape[2]), float(g.shape[2]), 1.0, float(g.brick_size), float(offset),
                   float(radii)])

    @staticmethod
    def segment(flat: Tensor, values: list, n_tables: int, o: tuple, d: tuple, t: Tensor,
                shadow: Tensor | bool) -> tuple[Tensor, Tensor]:
        """``(majorant, t_exit)`` ``(S,)`` of the brick (or empty cube) each ray ``o + t d`` (component form) is in
        at ``t``; ``shadow`` (per slot, or one bool for all) picks table 1 when there are two. ``values`` are
        :attr:`values` as numbers or 0-d tensors. ``t_exit > t`` always (a ray on a face moves on by the nudge)."""
        k = BrickTables.PER_TABLE
        tables = [values[i * k:(i + 1) * k] for i in range(n_tables)]

        def per_slot(j: int) -> Tensor:
            if isinstance(shadow, bool):
                return tables[1 if shadow and n_tables > 1 else 0][j] + torch.zeros_like(t)
            v0 = tables[0][j] + torch.zeros_like(t)
            if n_tables == 1:
                return v0
            return torch.where(shadow, tables[1][j] + torch.zeros_like(t), v0)

        table = [per_slot(j) for j in range(k)]
        n = flat.shape[0] - 1  # the flat input is padded by one zero (SceneInputs)
        radii = table[11].long()

        def reach(idx: Tensor) -> Tensor:  # half-width, in bricks, of the empty cube around the brick (0: none)
            r = (flat[(idx + radii).clamp(max=n)] - 1.0).clamp(min=0.0)
            return torch.where(radii > 0, r, torch.zeros_like(r))

        idx, t_exit = next_segment(table, o, d, t, reach_of=reach)
        return flat[idx], t_exit


def next_segment(table: list, o: tuple, d: tuple, t: Tensor, nudge: Tensor | None = None,
                 reach_of: Callable[[Tensor], Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """The one step of the brick walk, stateless: ``(index, t_exit)`` ``(N,)`` of the brick each ray ``o + t d``
    (component form) is in at ``t`` -- its index into the flat brick tables and the distance at which the ray
    leaves it. The compiled transport step calls it on every slot (:meth:`BrickTables.segment`); the eager code's
    walk (:class:`nrc.transport.tracking.MajorantWalk`) loops over it.

    ``table``: one grid's :attr:`BrickTables.values` entries (origin (3), last brick index (3), flat stride (3),
    brick edge, offset), as 0-d or per-ray tensors. The brick is the one holding the point ``nudge`` further on
    (default ``1e-4`` brick edges: a point on a face belongs to the brick it enters); ``t_exit >= t + nudge``.
    ``reach_of(index)``: the half-width, in bricks, of an empty cube centred on the brick that the ray may cross in
    this one step (:func:`skip_radius`); ``None``: one brick."""
    size = table[9]
    tn = t + (size * 1e-4 if nudge is None else nudge)
    idx = table[10].long()
    cells = []
    for a in range(3):
        c = ((o[a] + tn * d[a] - table[a]) / size).floor().nan_to_num(0.0, 0.0, 0.0).clamp(min=0.0)
        c = torch.minimum(c, table[3 + a])
        cells.append(c)
        idx = idx + c.long() * table[6 + a].long()
    reach = None if reach_of is None else reach_of(idx)
    t_exit = None
    for a, c in enumerate(cells):
        up = d[a] > 0
        shift = up.to(c.dtype) if reach is None else torch.where(up, 1.0 + reach, -reach)
        bound = table[a] + (c + shift) * size
        tb = torch.where(d[a] != 0, (bound - o[a]) / d[a], torch.full_like(t, math.inf))
        t_exit = tb if t_exit is None else torch.minimum(t_exit, tb)
    return idx, torch.maximum(t_exit, tn)
