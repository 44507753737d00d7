"""Free-flight sampling (delta tracking) and the batched tracking loop shared by the tracking estimators.

Rays are ``origin (N, 3)`` with unit ``direction (N, 3)``; distances ``t`` are world units along the ray.
All randomness comes from an explicit ``torch.Generator`` (same seed and inputs => same result), every tensor
is float32, and nothing loops over rays: the loop runs over events on a compacted set of the unfinished rays.

Majorants. Two modes share one loop (:func:`track`):

* ``"global"``: one constant majorant ``m = majorants.global_majorant`` on the ray's segment inside the box.
* ``"brick"``: the per-brick majorants of :class:`~nrc.volume.majorant.MajorantGrid`, walked by the stateless
  brick step :func:`nrc.volume.majorant.next_segment` (the compiled transport step's own). Each ray holds one
  exponential sample ``tau ~ Exp(1)`` of majorant optical depth.
  When ``tau`` exceeds what is left of the current brick (``majorant * distance to the brick exit``), the ray
  consumes that much and steps to the next brick (by memorylessness this is the same as restarting the
  exponential at the boundary, minus one random number); otherwise it takes a tentative collision at
  ``t + tau / majorant`` inside the brick and draws a new sample. A zero-majorant brick is crossed in one step
  with no lookup, and so is the whole empty cube around it: :func:`~nrc.volume.majorant.skip_radius` stores per brick the radius
  ``r`` of the cube of empty bricks centred on it, and the ray jumps to that cube's exit.

The loop does one event per unfinished ray and iteration (a brick step for some rays, a lookup for the others,
each on its compacted subset); finished rays are retired from the working set at once. Expected work is
``(bricks crossed + majorant optical depth)`` per ray; every step consumes either a brick or an ``Exp(1)``
share of a finite majorant optical depth, so the loop terminates (there is no step cap and no forced
collision).

Every looked-up ``sigma_t`` is checked against the majorant that was used for it; an underestimate raises
:class:`MajorantError` (never clamped).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from nrc.volume.majorant import BrickTables, next_segment, skip_radius

if TYPE_CHECKING:  # pragma: no cover
    from nrc.volume.grid import DensityGrid
    from nrc.volume.majorant import MajorantGrid

MODES = ("global", "brick")
DEFAULT_MODE = "brick"  # faster on both the dense and the sparse cloud (docs/transmittance.md)

# Tolerances of the majorant check. Brick bounds are tight (no dilation), so a point rounded onto a brick face
# may pick up a hair of the neighbouring brick's density: relative 1e-3 plus 1e-4 of the global majorant.
MAJORANT_RTOL = 1e-3
MAJORANT_ATOL = 1e-4


class MajorantError(RuntimeError):
    """A looked-up extinction exceeded the majorant used to sample it (the majorant grid is wrong or stale)."""


@dataclass
class TrackingStats:
    """Work counters of one call (summed over its chunks).

    Attributes:
        rays: rays that had a non-empty segment inside the box.
        lookups: extinction lookups performed (``sigma_t`` evaluations, including the ones wasted by
            block stepping and by frozen rays still in the working set): the cost.
        collisions: tentative collisions inside the rays' segments that the estimator used: the algorithm's
            own lookup count.
        iterations: loop iterations (rounds of kernel launches).
        advances: brick steps of the majorant walk (rays x bricks crossed).
    """

    rays: int = 0
    lookups: int = 0
    collisions: int = 0
    iterations: int = 0
    advances: int = 0

    def add(self, other: TrackingStats) -> None:
        self.rays += other.rays
        self.lookups += other.lookups
        self.collisions += other.collisions
        self.iterations += other.iterations
        self.advances += other.advances


def _as_col(value: float | Tensor | None, like: Tensor, default: float) -> Tensor:
    """A float, ``(N,)`` tensor or ``None`` as an ``(N,)`` float32 tensor on ``like``'s device."""
    if value is None:
        value = default
    v = torch.as_tensor(value, dtype=torch.float32, device=like.device)
    return v.expand(like.shape[0]) if v.dim() == 0 else v


def clip_segments(
    grid: DensityGrid, origin: Tensor, direction: Tensor, t0: float | Tensor | None, t1: float | Tensor | None
) -> tuple[Tensor, Tensor, Tensor]:
    """Clip ray segments ``[t0, t1]`` to the density box.

    Returns ``(o, a, b)``: shifted origins ``o = origin + t0 * direction`` and the clipped segment ``[a, b]``
    relative to them (``0 <= a <= b``, ``a == b`` for rays that miss the box or whose segment lies outside it),
    so that ``t = t0 + a`` is the entry distance along the original ray. ``t0`` defaults to 0 and ``t1`` to
    infinity (a ray to the box exit).
    """
    origin = origin.to(torch.float32)
    direction = direction.to(torch.float32)
    t0v = _as_col(t0, origin, 0.0)
    t1v = _as_col(t1, origin, math.inf)
    o = origin + t0v[:, None] * direction if t0 is not None else origin
    near, far = grid.box.intersect(o, direction)
    far = torch.minimum(far, t1v - t0v)
    empty = ~(far > near)
    zero = torch.zeros_like(near)
    return o, torch.where(empty, zero, near), torch.where(empty, zero, far)


def ratio_step(T: Tensor, sigma: Tensor, majorant: Tensor, u: Tensor | None = None,
               threshold: Tensor | float | None = None) -> Tensor:
    """One tentative collision of ratio tracking, written once for the eager estimators (:func:`track`) and the
    compiled transport step's shadow rays: ``T (1 - sigma / majorant)`` (``sigma`` may exceed the majorant by
    rounding only -- beyond :data:`MAJORANT_RTOL` the eager loop raises -- and such a null-collision probability is
    0, not a tiny negative number); then, with a ``threshold``, the roulette: a weight below it survives with
    probability ``T`` (the uniform ``u``) and goes on with 1, else stops with 0 (unbiased)."""
    T = T * (1.0 - sigma / majorant.clamp(min=1e-30)).clamp(min=0.0)
    if threshold is not None:
        T = torch.where(T < threshold, (u < T).to(T.dtype), T)
    return T


# ---------------------------------------------------------------------------------------------- core loop
DELTA, RATIO, RESIDUAL, BOUNDS = "delta", "ratio", "residual", "bounds"

# Columns of the per-ray walk state (one float32 row per ray, so compaction is a single index_select).
_T, _TAU, _RATE, _CTRL, _TAUC, _PROD, _B, _TX = 0, 1, 2, 3, 4, 5, 6, 7  # _TX: where the current segment ends
_O = slice(8, 11)
_D = slice(11, 14)
_RES = 14  # delta: collision distance; bounds: the brick's minorant
_NCOL = 15
_FOLD = 1e30  # residual ratio tracking: prod above this takes exp(-tauc) in (see track)


class MajorantWalk:
    """The batched majorant walk of the eager code (the estimators, equi-angular sampling, the optical-depth
    bounds) over a :class:`~nrc.volume.majorant.MajorantGrid`: the rays advance lazily, one brick (or one empty
    cube, :func:`~nrc.volume.majorant.skip_radius`) per inner step, only where the current exponential sample reaches past the current
    brick. Each step is :func:`nrc.volume.majorant.next_segment`, the same stateless brick step the compiled
    transport step runs (the state is the ray's point: no DDA bookkeeping across compaction).
    :func:`majorant_segments` iterates it segment by segment."""

    def __init__(self, grid, majorants, kind: str, mode: str) -> None:
        self.grid = grid
        self.kind = kind
        self.brick = mode == "brick"
        self.m_glob = float(majorants.global_majorant)
        if self.brick:
            maj = majorants.majorant.reshape(-1).to(torch.float32)
            mnr = majorants.minorant.reshape(-1).to(torch.float32)
            self.min_grid = None
            if kind == RESIDUAL:
                self.rate_grid, self.ctrl_grid = 0.5 * (maj - mnr), 0.5 * (maj + mnr)
            elif kind == BOUNDS:  # no collisions; integrate the majorant (as "control") and the minorant
                self.rate_grid, self.ctrl_grid, self.min_grid = torch.zeros_like(maj), maj, mnr
            else:
                self.rate_grid, self.ctrl_grid = maj, None
            self.size = float(majorants.brick_size)
            # the grid's brick table (origin, last index, strides, edge, offset 0) as 0-d tensors
            values = BrickTables.grid_values(majorants)
            self.table = torch.tensor(values, dtype=torch.float32, device=maj.device).unbind(0)
            self.skip_grid = skip_radius(majorants).reshape(-1)  # cached per majorant grid

    def _reach(self, flat: Tensor) -> Tensor:
        """Half-width in bricks of the empty cube around bricks ``flat`` (0: a non-empty brick)."""
        return (self.skip_grid[flat] - 1.0).clamp(min=0.0)

    def _enter(self, S: Tensor) -> None:
        """The brick (or empty cube) the rows of ``S`` are in at their ``t``: its end and its rates."""
        t, b = S[:, _T], S[:, _B]
        nudge = torch.minimum((b - t).clamp(min=0.0), torch.full_like(t, 1e-4 * self.size))
        o = (S[:, _O.start], S[:, _O.start + 1], S[:, _O.start + 2])
        d = (S[:, _D.start], S[:, _D.start + 1], S[:, _D.start + 2])
        flat, S[:, _TX] = next_segment(self.table, o, d, t, nudge, self._reach)
        S[:, _RATE] = self.rate_grid[flat]
        if self.ctrl_grid is not None:
            S[:, _CTRL] = self.ctrl_grid[flat]
        if self.min_grid is not None:
            S[:, _RES] = self.min_grid[flat]

    def init_state(self, o: Tensor, d: Tensor, a: Tensor, b: Tensor, tau: Tensor) -> Tensor:
        n = o.shape[0]
        S = torch.zeros(n, _NCOL, dtype=torch.float32, device=o.device)
        S[:, _T] = a
        S[:, _TAU] = tau
        S[:, _PROD] = 1.0
        S[:, _B] = b
        S[:, _O] = o
        S[:, _D] = d
        S[:, _RES] = b
        if not self.brick:
            S[:, _RATE] = self.m_glob
            S[:, _TX] = math.inf
            return S
        self._enter(S)
        return S

    @staticmethod
    def needs_advance(S: Tensor) -> Tensor:
        """Rays whose remaining exponential sample reaches past their current brick (or segment end)."""
        t_exit = torch.minimum(S[:, _TX], S[:, _B])
        return S[:, _TAU] >= S[:, _RATE] * (t_exit - S[:, _T])

    def advance(self, S: Tensor, sub: Tensor | None) -> None:
        """Move the rays ``sub`` (row indices of ``S``, in place) across their current segment: their exponential
        sample reaches past it, so they consume its majorant optical depth and enter the next brick (or reach their
        segment end, ``t = b``). A zero-majorant brick is crossed in this one step, and so is the whole empty cube
        around it (:func:`~nrc.volume.majorant.skip_radius`). ``sub=None`` moves every row (in place, no gather)."""
        R = S if sub is None else S.index_select(0, sub)
        t = R[:, _T]
        b = R[:, _B]
        t_exit = torch.maximum(torch.minimum(R[:, _TX], b), t)
        dt = t_exit - t
        R[:, _TAU].sub_(R[:, _RATE] * dt).clamp_(min=0.0)
        if self.kind == RESIDUAL:
            R[:, _TAUC].add_(R[:, _CTRL] * dt)
        elif self.kind == BOUNDS:
            R[:, _TAUC].add_(R[:, _CTRL] * dt)
            R[:, _PROD].add_(R[:, _RES] * dt)
        R[:, _T] = t_exit
        if self.brick:
            self._enter(R)
        if sub is not None:
            S.index_copy_(0, sub, R)


def majorant_segments(majorants: MajorantGrid, origin: Tensor, direction: Tensor, a: Tensor,
                      b: Tensor) -> Iterator[tuple[Tensor, Tensor, Tensor, Tensor, Tensor]]:
    """The walk's segments of ``[a, b]`` ``(N,)`` (inside the box), in order: yields ``(live, t0, t1, majorant,
    minorant)`` ``(N,)`` per step, ``live`` the rays whose segment is not used up (the others yield
    ``t0 = t1``, majorant 0). A run of empty bricks comes as one segment of majorant 0; the segments of a ray
    tile its ``[a, b]`` exactly once. Loops over steps (at most the bricks crossed), never over rays."""
    walk = MajorantWalk(majorants.grid, majorants, BOUNDS, "brick")
    S = walk.init_state(origin, direction, a, b, torch.zeros_like(a))
    live = b > a
    while bool(live.any()):
        t0, maj, mnr = S[:, _T].clone(), S[:, _CTRL].clone(), S[:, _RES].clone()
        walk.advance(S, None)
        zero = torch.zeros_like(t0)
        yield live, t0, torch.where(live, S[:, _T], t0), torch.where(live, maj, zero), torch.where(live, mnr, zero)
        live = live & (S[:, _T] < S[:, _B])


def optical_depth_bounds(
    majorants: MajorantGrid, origin: Tensor, direction: Tensor, a: Tensor, b: Tensor
) -> tuple[Tensor, Tensor]:
    """``(tau_major, tau_minor)`` ``(N,)``: the brick majorant and minorant integrated over ``[a, b]`` (inside the
    box), by the brick walk of this module (compacted, with empty-space jumps)."""
    tau_major = torch.zeros_like(a)
    tau_minor = torch.zeros_like(a)
    idx = torch.nonzero(b > a).squeeze(1)
    if idx.numel() == 0 or not majorants.global_majorant > 0:
        return tau_major, tau_minor
    walk = MajorantWalk(majorants.grid, majorants, BOUNDS, "brick")
    S = walk.init_state(origin[idx], direction[idx], a[idx], b[idx], torch.zeros(idx.numel(), device=a.device))
    S[:, _PROD] = 0.0
    while S.shape[0]:
        walk.advance(S, None)
        fin = S[:, _T] >= S[:, _B]
        if bool(fin.any()):
            f = torch.nonzero(fin).squeeze(1)
            tau_major[idx[f]] = S[f, _TAUC]
            tau_minor[idx[f]] = S[f, _PROD]
            keep = torch.nonzero(~fin).squeeze(1)
            S, idx = S.index_select(0, keep), idx[keep]
    return tau_major, tau_minor


def track(
    grid: DensityGrid,
    majorants: MajorantGrid,
    origin: Tensor,
    direction: Tensor,
    a: Tensor,
    b: Tensor,
    gen: torch.Generator,
    kind: str,
    mode: str = DEFAULT_MODE,
    roulette_threshold: float = 0.0,
    stats: TrackingStats | None = None,
) -> tuple[Tensor, Tensor] | Tensor:
    """Run a tracking estimator over already clipped segments ``[a, b]`` (see :func:`clip_segments`).

    Args:
        kind: ``"delta"`` (free-flight sampling: returns ``(t, collided)`` with ``t`` relative to ``origin``,
            ``t = b`` where nothing collided), ``"ratio"`` (ratio tracking: returns the weight ``T``) or
            ``"residual"`` (residual ratio tracking with per-brick control ``(maj + min)/2`` and residual
            majorant ``(maj - min)/2``; needs ``mode="brick"``; returns ``T``).
        mode: ``"global"`` or ``"brick"`` majorant.
        roulette_threshold: ratio/residual only: when the running weight of a ray drops below it (checked after
            each tentative collision), the ray survives with probability equal to the weight and continues with
            weight 1, else it stops with weight 0 (unbiased). 0 disables.
        stats: if given, the work counters are added to it.
    """
    if mode not in MODES:
        raise ValueError(f"majorant mode must be one of {MODES}, got {mode!r}")
    if kind not in (DELTA, RATIO, RESIDUAL):
        raise ValueError(f"unknown tracking kind {kind!r}")
    if kind == RESIDUAL and mode != "brick":
        raise ValueError("residual ratio tracking needs per-brick controls (mode='brick')")
    thr = float(roulette_threshold)
    n = origin.shape[0]
    dev = origin.device
    st = TrackingStats()
    t_out = b.clone()
    hit_out = torch.zeros(n, dtype=torch.bool, device=dev)
    w_out = torch.ones_like(a)
    idx = torch.nonzero(b > a).squeeze(1)
    st.rays = int(idx.numel())
    if st.rays == 0 or not majorants.global_majorant > 0:  # zero majorant everywhere: no collision, T = 1
        if stats is not None:
            stats.add(st)
        return (t_out, hit_out) if kind == DELTA else w_out
    walk = MajorantWalk(grid, majorants, kind, mode)
    tau0 = -torch.log1p(-torch.rand(idx.numel(), generator=gen, device=dev))
    S = walk.init_state(origin[idx], direction[idx], a[idx], b[idx], tau0)
    lim_scale = 1.0 + MAJORANT_RTOL
    lim_abs = MAJORANT_ATOL * majorants.global_majorant

    def retire(S: Tensor, idx: Tensor, done: Tensor) -> tuple[Tensor, Tensor]:
        fin = torch.nonzero(done).squeeze(1)
        rows = S.index_select(0, fin)
        ids = idx[fin]
        if kind == DELTA:
            t_out[ids] = rows[:, _RES]
            hit_out[ids] = rows[:, _RES] < rows[:, _B]
        elif kind == RATIO:
            w_out[ids] = rows[:, _PROD]
        else:
            w_out[ids] = torch.exp(-rows[:, _TAUC]) * rows[:, _PROD]
        keep = torch.nonzero(~done).squeeze(1)
        return S.index_select(0, keep), idx[keep]

    advances = 0
    iters = 0
    while S.shape[0]:
        # One event per ray and iteration: a brick step for the rays whose sample lies beyond their brick,
        # a tentative collision for the others.
        iters += 1
        need = walk.needs_advance(S)
        mv = torch.nonzero(need).squeeze(1)
        rd = torch.nonzero(~need).squeeze(1)
        nmv, nrd = int(mv.numel()), int(rd.numel())
        done = torch.zeros(S.shape[0], dtype=torch.bool, device=dev)
        m = S.shape[0]
        if nmv:
            advances += nmv
            walk.advance(S, None if nmv == m else mv)
            done[mv] = S[mv, _T] >= S[mv, _B]
        if nrd:
            st.lookups += nrd
            st.collisions += nrd
            R = S if nrd == m else S.index_select(0, rd)  # (a view when every ray collides: updated in place)
            u = torch.rand((nrd, 3), generator=gen, device=dev)
            t, rate = R[:, _T], R[:, _RATE]  # rate > 0: the sample fell short of the brick end
            tc = t + R[:, _TAU] / rate
            sigma = grid.sigma_t(R[:, _O] + tc[:, None] * R[:, _D])
            maj = rate + R[:, _CTRL] if kind == RESIDUAL else rate
            bad = sigma > maj * lim_scale + lim_abs
            if kind == DELTA:
                fin = u[:, 1] * rate < sigma
                R[:, _RES] = torch.where(fin, tc, R[:, _RES])
            elif kind == RATIO:
                w = ratio_step(R[:, _PROD], sigma, rate, u[:, 1], thr if thr > 0 else None)
                R[:, _PROD] = w
                fin = w == 0
            else:
                ctrl = R[:, _CTRL]
                tauc = R[:, _TAUC] + ctrl * (tc - t)
                prod = R[:, _PROD] * (1.0 - (sigma - ctrl) / rate).clamp(min=0.0)  # (rounding, as above)
                # the factors are <= 2: over thousands of collisions (a dense medium) prod would overflow while
                # exp(-tauc) underflows (0 x inf = NaN); fold the control's share in before (w unchanged)
                big = prod > _FOLD
                prod = torch.where(big, prod * torch.exp(-tauc), prod)
                tauc = torch.where(big, torch.zeros_like(tauc), tauc)
                w = torch.exp(-tauc) * prod
                if thr > 0:
                    small = w < thr
                    prod = torch.where(small, (u[:, 1] < w).to(w.dtype), prod)
                    tauc = torch.where(small, torch.zeros_like(tauc), tauc)
                    w = torch.where(small, prod, w)
                R[:, _TAUC] = tauc
                R[:, _PROD] = prod
                fin = w == 0
            R[:, _T] = tc
            R[:, _TAU] = -torch.log1p(-u[:, 0])
            if nrd != m:
                S.index_copy_(0, rd, R)
            done[rd] = fin
            nbad = int(bad.sum())
            if nbad:
                worst = float((sigma - maj)[bad].max())
                raise MajorantError(
                    f"sigma_t exceeded the {mode} majorant by {worst:g} at {nbad} lookup(s): "
                    "the majorant grid does not bound the density (stale density_scale?)"
                )
        if bool(done.any()):
            S, idx = retire(S, idx, done)
    st.iterations += iters
    st.advances += advances
    if stats is not None:
        stats.add(st)
    return (t_out, hit_out) if kind == DELTA else w_out


# ---------------------------------------------------------------------------------------------- public API
def sample_free_flight(
    grid: DensityGrid,
    majorants: MajorantGrid,
    origin: Tensor,
    direction: Tensor,
    t_max: float | Tensor | None,
    gen: torch.Generator,
    mode: str = DEFAULT_MODE,
    return_stats: bool = False,
) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, TrackingStats]:
    """Delta tracking: sample the distance to the first real collision along each ray.

    Args:
        grid: the density grid (``sigma_t`` lookups).
        majorants: a :class:`~nrc.volume.majorant.MajorantGrid` built for ``grid`` at its density scale.
        origin: ``(N, 3)`` ray origins (inside or outside the box).
        direction: ``(N, 3)`` unit directions.
        t_max: float, ``(N,)`` tensor or ``None`` (= infinity): only collisions before ``t_max`` count.
        gen: the random generator.
        mode: ``"brick"`` (per-brick majorants, the default: faster) or ``"global"``.
        return_stats: also return a :class:`TrackingStats`.

    Returns:
        ``(t, collided)``: ``(N,)`` float32 and bool. ``t`` is the collision distance from ``origin`` where
        ``collided``, else ``t_max`` (``inf`` if ``t_max`` is ``None``): the ray escaped the box or reached
        ``t_max``. The distance has density ``sigma_t(t) exp(-tau(t))`` on the segment.

    Raises:
        MajorantError: a looked-up ``sigma_t`` exceeded the majorant used.
    """
    direction = direction.to(torch.float32)
    o, a, b = clip_segments(grid, origin, direction, None, t_max)
    st = TrackingStats()
    t_rel, hit = track(grid, majorants, o, direction, a, b, gen, DELTA, mode, stats=st)
    t_end = _as_col(t_max, o, math.inf)
    t = torch.where(hit, t_rel, t_end)
    return (t, hit, st) if return_stats else (t, hit)
