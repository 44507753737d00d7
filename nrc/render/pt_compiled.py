"""The compiled backend of ``renderer=pt``: a fixed-shape per-slot state machine (``renderer.backend``).

Same estimator as the eager :class:`~nrc.render.pt.PathTracer` (SCENE.md; ``docs/path_tracer.md``): delta-tracked
free flights, next-event estimation at every real scattering vertex (one light chosen uniformly, ratio-tracking
transmittance with the configured roulette), the power heuristic against phase-sampled environment escapes,
camera rays that escape see the environment with weight 1, ``max_scatter`` real scattering events, the
last-vertex continuation only when an environment light exists, optional Russian roulette. Differences are in
execution only:

* **Per-path shadow rays.** Each slot holds one path *and* its pending shadow ray. An iteration advances every
  slot by exactly one tracking step: a ratio-tracking step of the shadow ray when one is pending, otherwise a
  delta-tracking step of the free flight. A real collision queues the vertex's shadow ray in the same slot
  (its contribution weight is known at the vertex; the transmittance multiplies it when the ray finishes) and
  samples the continuation, which resumes once the shadow ray is done.
* **Brick majorants without traversal state** (:class:`BrickTables`): each step looks up the brick its ray is
  in from the current point and either samples a tentative collision against that brick's majorant or moves
  the ray to the brick's exit (an empty brick costs one step), so a step is the same branch-free arithmetic
  for every slot. Steps that need no density (brick crossings, idle slots) look it up at the box corner,
  whose voxels stay in cache: only tentative collisions pay the grid's memory traffic. The grids are the eager tracer's
  (``renderer.brick``, ``renderer.free_flight``); shadow rays always use the bricks.
* **Counter-based RNG** (:mod:`nrc.transport.rng`): the numbers of a path depend on ``(seed, sample id, step
  counter)`` only, so the image does not depend on the number of slots or on the refill cadence.
* **Scattering** is a second compiled function run after every ``SCATTER_EVERY``-th tracking call on the
  slots waiting at a real collision (a few percent of them): the tracking step itself only looks up the
  density and updates weights.
* **Refill** happens outside the compiled functions, every ``REFILL_EVERY``-th call of ``steps_per_call``
  steps: finished paths add their radiance to their pixel and
  their slots take new camera samples. Once the camera queue is
  empty the state is compacted whenever fewer than half the slots are live (dynamic shapes: no recompile).

State: a float32 ``(24, S)`` and an int64 ``(8, S)`` tensor, one contiguous row per field so that the
compiled kernels vectorise over slots (136 bytes a slot, 9 MB at 65,536 slots), plus the ``(H x W x 3)``
image; the compiled functions' temporaries are of the same order. Unsupported configurations (see
:func:`unsupported_reason`) run on the eager backend. Units: world units for
positions and distances, radiance in linear RGB.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from nrc.render.result import RenderResult
from nrc.transport.light_sampling import LightSampler
from nrc.transport.phase import hg_pdf, hg_sample_cos
from nrc.transport.rng import path_key, uniforms
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import MajorantGrid

if TYPE_CHECKING:  # pragma: no cover
    from nrc.render.pt import PathTracer

# float columns of the state
_O, _D, _T, _TMAX, _BETA, _PDF, _L = slice(0, 3), slice(3, 6), 6, 7, slice(8, 11), 11, slice(12, 15)
_WI, _TS, _TSE, _TR, _CSH = slice(15, 18), 18, 19, 20, slice(21, 24)
NF = 24
# int columns: pixel, RNG key, step counter, scattering events, free flight pending, shadow pending,
# slot holds an unharvested path, shadow steps taken
_PIX, _KEY, _CNT, _N, _FF, _SH, _OCC, _NSH = range(8)
NI = 8
REFILL_EVERY = 4  # calls between refills while the camera queue lasts (finished slots idle ~1.5 steps)
# calls between scattering passes: slots at a vertex wait ~0.5 step longer (+3.6 % slot-steps) for half the
# passes' fixed cost (nonzero, gathers; eager and single-threaded): ~+15 % samples/s at 2 threads (benchmarks.md)
SCATTER_EVERY = 2
MIN_SLOTS = 64  # compaction never goes below this (dynamic-shape kernels specialise sizes 0 and 1)


V3 = tuple[Tensor, Tensor, Tensor]  # a batch of 3-vectors as three (S,) tensors (x, y, z)


def trilinear(density: Tensor, lo: tuple[float, float, float], hi: tuple[float, float, float], x: V3) -> Tensor:
    """``D(x)`` ``(S,)`` at world points ``x`` by explicit gathers on the flattened ``(nx, ny, nz)`` grid; the
    same field as :meth:`DensityGrid.lookup` (``grid_sample``, ``align_corners=False``, border padding):
    cell-centred samples, clamped within half a cell of the faces, exactly zero outside the box ``[lo, hi]``.
    Non-finite points give 0 (indices are clamped, so every gather is in bounds)."""
    shape = density.shape
    flat = density.reshape(-1)
    inside = None
    i0s, i1s, fs = [], [], []
    for a in range(3):
        s = (x[a] - lo[a]) / (hi[a] - lo[a])
        ok = (s >= 0) & (s <= 1)
        inside = ok if inside is None else inside & ok
        u = (s * shape[a] - 0.5).nan_to_num(0.0, 0.0, 0.0).clamp(0.0, shape[a] - 1.0)
        f = u.floor()
        i0 = f.long()
        i0s.append(i0)
        i1s.append((i0 + 1).clamp(max=shape[a] - 1))
        fs.append(u - f)
    sx, sy = shape[1] * shape[2], shape[2]
    bx = (i0s[0] * sx, i1s[0] * sx)
    by = (i0s[1] * sy, i1s[1] * sy)
    fx, fy, fz = fs

    def lerp_z(i: int, j: int) -> Tensor:
        base = bx[i] + by[j]
        return flat[base + i0s[2]] * (1 - fz) + flat[base + i1s[2]] * fz

    v = (lerp_z(0, 0) * (1 - fy) + lerp_z(0, 1) * fy) * (1 - fx) + (lerp_z(1, 0) * (1 - fy) + lerp_z(1, 1) * fy) * fx
    return torch.where(inside, v, torch.zeros_like(v))


def box_exit(lo: tuple[float, float, float], hi: tuple[float, float, float], o: V3, d: V3) -> Tensor:
    """``t_far`` ``(S,)`` of :meth:`nrc.volume.box.Box.intersect` for rays ``o + t d`` (0 when the ray misses
    the box or it lies behind), in component form."""
    big = torch.finfo(torch.float32).max
    t_near, t_far = None, None
    for a in range(3):
        inv = 1.0 / d[a]
        t0, t1 = (lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv
        zero = d[a] == 0
        inside = (o[a] >= lo[a]) & (o[a] <= hi[a])
        tmin = torch.where(zero, torch.where(inside, -big, big), torch.minimum(t0, t1))
        tmax = torch.where(zero, torch.where(inside, big, -big), torch.maximum(t0, t1))
        t_near = tmin if t_near is None else torch.maximum(t_near, tmin)
        t_far = tmax if t_far is None else torch.minimum(t_far, tmax)
    t_near = t_near.clamp(min=0.0)
    return torch.where(t_far > t_near, t_far, torch.zeros_like(t_far))


class BrickTables:
    """The majorant grids of a tracer in the step's form: flat per-brick majorants and per-grid constants.

    Table 0 serves free flights and table 1 shadow rays (one table when both use the same grid, i.e.
    ``renderer.free_flight=brick``; with ``global`` free flights use a single box-sized brick). A step finds
    a ray's brick from its current point, nudged ``1e-4`` brick edges along the ray (a point on a face
    belongs to the brick it enters), and the distance to that brick's exit. No traversal state is carried
    between steps, so refills, shadow rays and compaction need no bookkeeping.

    Args:
        free_flight, shadow: the :class:`~nrc.volume.majorant.MajorantGrid` of each kind of ray.
    """

    def __init__(self, free_flight: MajorantGrid, shadow: MajorantGrid) -> None:
        grids = [free_flight] if shadow is free_flight else [free_flight, shadow]
        self.flat = torch.cat([g.majorant.reshape(-1) for g in grids]).float().contiguous()
        # per table and axis: origin, last brick index, flat stride; per table: brick edge, offset into flat
        self.origin = [tuple(float(v) for v in g.origin.tolist()) for g in grids]
        self.last = [tuple(float(n - 1) for n in g.shape) for g in grids]
        self.stride = [(g.shape[1] * g.shape[2], g.shape[2], 1) for g in grids]
        self.size = [float(g.brick_size) for g in grids]
        self.offset = [0, free_flight.majorant.numel()][: len(grids)]

    def segment(self, o: V3, d: V3, t: Tensor, shadow: Tensor) -> tuple[Tensor, Tensor]:
        """``(majorant, t_exit)`` ``(S,)`` of the brick each ray ``o + t d`` is in at ``t`` (``shadow`` picks
        table 1 per slot); ``t_exit > t`` always (a ray on a face moves on by the nudge)."""
        two = len(self.size) == 2

        def per_slot(values: list[Any]) -> Any:
            return torch.where(shadow, values[1], values[0]) if two else values[0]

        size = per_slot(self.size)
        tn = t + size * 1e-4
        idx = per_slot(self.offset)
        t_exit = None
        for a in range(3):
            org = per_slot([v[a] for v in self.origin])
            c = ((o[a] + tn * d[a] - org) / size).floor().nan_to_num(0.0, 0.0, 0.0).clamp(min=0.0)
            last = per_slot([v[a] for v in self.last])
            c = torch.minimum(c, last) if two else c.clamp(max=last)
            bound = org + (c + (d[a] > 0).to(c.dtype)) * size
            tb = torch.where(d[a] != 0, (bound - o[a]) / d[a], torch.full_like(t, math.inf))
            t_exit = tb if t_exit is None else torch.minimum(t_exit, tb)
            idx = idx + c.long() * per_slot([v[a] for v in self.stride])
        return self.flat[idx], torch.maximum(t_exit, tn)


def hg_sample3(g: float, d: V3, u0: Tensor, u1: Tensor) -> tuple[V3, Tensor]:
    """:func:`nrc.transport.phase.hg_sample` in component form: ``(new direction, pdf)``."""
    mu, sin_t, pdf = hg_sample_cos(g, u0)
    x, y, z = d
    sign = torch.copysign(torch.ones_like(z), z)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = (1.0 + sign * x * x * a, sign * b, -sign * x)
    bb = (b, sign + y * y * a, -y)
    phi = (2.0 * math.pi) * u1
    c, s = sin_t * torch.cos(phi), sin_t * torch.sin(phi)
    return (c * t[0] + s * bb[0] + mu * x, c * t[1] + s * bb[1] + mu * y, c * t[2] + s * bb[2] + mu * z), pdf


def _power(a: Tensor, b: Tensor | float) -> Tensor:
    """Power heuristic ``a^2 / (a^2 + b^2)``, 1 where both are zero (as :func:`nrc.render.pt.power_heuristic`)."""
    a2, b2 = a * a, b * b
    den = a2 + b2
    return torch.where(den > 0, a2 / den.clamp(min=1e-30), torch.ones_like(den))


def _pick(m: Tensor | None, new: V3, old: V3) -> V3:
    """Component-wise ``where(m, new, old)``; ``m=None`` takes ``new`` (a light chosen with probability 1)."""
    if m is None:
        return tuple(n if isinstance(n, Tensor) else torch.full_like(o, n) for n, o in zip(new, old))
    return tuple(torch.where(m, n, o) for n, o in zip(new, old))


class Lights3:
    """:class:`LightSampler` in component form for directional, point and uniform environment lights.

    Args:
        lights: the eager sampler (its lights are read once; lat-long maps are not supported here).
    """

    def __init__(self, lights: LightSampler) -> None:
        if lights.env_maps:
            raise ValueError("lat-long environment maps have no compiled light sampler")
        vec = lambda t: tuple(float(v) for v in t.tolist())  # noqa: E731
        self.directional = [(vec(-lt.direction), vec(lt.irradiance)) for lt in lights.directional]
        self.points = [(vec(lt.position), vec(lt.intensity)) for lt in lights.points]
        self.env = vec(lights.uniform_env) if lights.has_uniform_env else None
        self.n_lights = lights.n_lights
        self.has_env = lights.has_env
        # P(select) x solid-angle pdf of NEE producing any direction (uniform sky only)
        self.env_pdf = 1.0 / (4.0 * math.pi) / self.n_lights if self.has_env else 0.0

    def sample(self, x: V3, u_sel: Tensor, u1: Tensor, u2: Tensor) -> tuple[V3, Tensor, V3, Tensor, Tensor]:
        """``(wi, distance, weight, light_pdf, is_env)`` as :meth:`LightSampler.sample` with uniforms
        ``u = (u_sel, u1, u2, -)``."""
        n = self.n_lights
        k = (u_sel * n).long().clamp(max=n - 1) if n > 1 else None
        zero = torch.zeros_like(x[0])
        wi: V3 = (zero, zero + 1.0, zero)
        dist = torch.full_like(zero, math.inf)
        weight: V3 = (zero, zero, zero)
        is_env = torch.zeros_like(zero, dtype=torch.bool)
        idx = 0
        for direction, irradiance in self.directional:
            m = None if k is None else k == idx
            wi, weight = _pick(m, direction, wi), _pick(m, irradiance, weight)
            idx += 1
        for position, intensity in self.points:
            m = None if k is None else k == idx
            to = (position[0] - x[0], position[1] - x[1], position[2] - x[2])
            r2 = (to[0] * to[0] + to[1] * to[1] + to[2] * to[2]).clamp(min=1e-12)
            r = torch.sqrt(r2)
            wi = _pick(m, (to[0] / r, to[1] / r, to[2] / r), wi)
            dist = r if m is None else torch.where(m, r, dist)
            weight = _pick(m, (intensity[0] / r2, intensity[1] / r2, intensity[2] / r2), weight)
            idx += 1
        if self.env is not None:
            m = None if k is None else k == idx
            z = 1.0 - 2.0 * u1
            rr = torch.sqrt((1.0 - z * z).clamp(min=0.0))
            phi = 2.0 * math.pi * u2
            wi = _pick(m, (rr * torch.cos(phi), rr * torch.sin(phi), z), wi)
            is_env = torch.ones_like(is_env) if m is None else m
            pdf = self.env_pdf
            light_pdf = torch.where(is_env, pdf, zero)
            weight = tuple(torch.where(is_env, e / pdf, w * n) for e, w in zip(self.env, weight))
        else:
            light_pdf = zero
            weight = tuple(w * n for w in weight)
        return wi, dist, weight, light_pdf, is_env


class WavefrontStep:
    """The per-slot state machine as two pure functions of the ``(NF, S)`` float32 and ``(NI, S)`` int64
    state: :meth:`track` (one tracking step of every slot) and :meth:`scatter` (the few slots that met a real
    collision: NEE request, roulette, phase sampling; run on that subset only, so the common step stays
    small). Written per component (no ``(S, 3)`` tensors, no reductions), so that inductor fuses each into a
    few loops over the slots.

    Args:
        grid: the density grid; bricks: its majorant tables (free flights, shadow rays); lights: the light
        sampler; albedo, g: medium; max_scatter: integrator limit;
        roulette_threshold: ratio-tracking roulette (0 = off); rr_start: Russian roulette from this many
        scattering events on (``None`` = off).
    """

    def __init__(
        self,
        grid: DensityGrid,
        bricks: BrickTables,
        lights: LightSampler,
        albedo: float,
        g: float,
        max_scatter: int,
        roulette_threshold: float,
        rr_start: int | None,
    ) -> None:
        self.density = grid.density
        self.lo = tuple(float(v) for v in grid.box.lo.tolist())
        self.hi = tuple(float(v) for v in grid.box.hi.tolist())
        self.scale = float(grid.density_scale)
        self.bricks = bricks
        self.lights = Lights3(lights)
        self.albedo, self.g = float(albedo), float(g)
        self.max_scatter = int(max_scatter)
        self.thr = float(roulette_threshold)
        self.rr_start = rr_start
        # uniforms per step: distance, real/null (shadow: roulette), phase (2), then Russian roulette and the
        # light choice (several lights) and a uniform-sky direction (2) only when needed
        self.lanes = 4 + (rr_start is not None) + (lights.n_lights > 1) + 2 * lights.has_uniform_env

    def sigma_t(self, x: V3) -> Tensor:
        """Extinction ``(S,)`` per world unit at world points ``x``."""
        return self.scale * trilinear(self.density, self.lo, self.hi, x)

    def track(self, F: Tensor, I: Tensor) -> tuple[Tensor, Tensor]:
        """One tracking step for every slot: its shadow ray if one is pending, else its free flight. Slots
        whose free flight meets a real collision are left waiting (``FF = 2``, ``o`` = the vertex) for
        :meth:`scatter`."""
        lights = self.lights
        row = F.unbind(0)
        o, d, t, tmax = row[0:3], row[3:6], row[_T], row[_TMAX]
        beta, pdf, L = row[8:11], row[_PDF], row[12:15]
        wi, ts, tse, Tr, csh = row[15:18], row[_TS], row[_TSE], row[_TR], row[21:24]
        n = I[_N]
        ff, sh = I[_FF] == 1, I[_SH] != 0
        cnt = I[_CNT] + (ff | sh).long()
        u0, u1 = uniforms(I[_KEY], cnt, 2)
        zero = torch.zeros_like(t)

        # One step against the majorant m of the ray's current brick: a tentative collision inside the brick
        # (hit), or a move to the brick's exit (memoryless restart there), or the end of the ray (passed).
        run_ff = ff & ~sh
        dr = _pick(sh, wi, d)
        tr = torch.where(sh, ts, t)
        te = torch.where(sh, tse, tmax)
        m, t_brick = self.bricks.segment(o, dr, tr, sh)
        seg_end = torch.minimum(t_brick, te)
        tc = torch.where(m > 0, tr - torch.log1p(-u0) / m.clamp(min=1e-30), torch.full_like(tr, math.inf))
        hit = tc < seg_end
        passed = ~hit & (seg_end >= te)
        tx = torch.where(hit, tc, seg_end)
        x = (o[0] + tx * dr[0], o[1] + tx * dr[1], o[2] + tx * dr[2])
        # Only tentative collisions of running rays need the density; the others look up the box corner,
        # whose voxels stay in cache (a brick crossing or an idle slot costs no memory traffic).
        need = hit & (run_ff | sh)
        sigma = self.sigma_t(_pick(need, x, self.lo))
        nul = (1.0 - sigma / m.clamp(min=1e-30)).clamp(min=0.0)

        # Shadow rays: ratio tracking with roulette; the contribution lands when the ray ends.
        Tn = torch.where(hit, Tr * nul, Tr)
        if self.thr > 0:
            Tn = torch.where(hit & (Tn < self.thr), (u1 < Tn).to(Tn.dtype), Tn)
        sh_end = sh & (passed | (Tn == 0))
        L = tuple(Lc + torch.where(sh_end, c * Tn, zero) for Lc, c in zip(L, csh))
        ts = torch.where(sh, tx, ts)
        Tr = torch.where(sh, Tn, Tr)

        # Free flights: escape (environment, MIS unless a camera ray), null or real collision.
        esc = run_ff & passed
        real = run_ff & hit & (u1 * m < sigma)
        t = torch.where(run_ff & ~passed & ~real, tx, t)
        if lights.env is not None:
            w = torch.where(pdf > 0, _power(pdf, lights.env_pdf), torch.ones_like(pdf))
            L = tuple(Lc + torch.where(esc, b * (e * w), zero) for Lc, b, e in zip(L, beta, lights.env))
        at_limit = real & (n >= self.max_scatter)  # the continuation of the last vertex collided: done
        scat = real & ~at_limit
        o = _pick(scat, x, o)
        ff_new = torch.where(scat, 2, torch.where(esc | at_limit, 0, I[_FF]))

        F = torch.stack([*o, *d, t, tmax, *beta, pdf, *L, *wi, ts, tse, Tr, *csh])
        I = torch.stack([I[_PIX], I[_KEY], cnt, n, ff_new, (sh & ~sh_end).long(), I[_OCC], I[_NSH] + sh.long()])
        return F, I

    def scatter(self, F: Tensor, I: Tensor) -> tuple[Tensor, Tensor]:
        """Real scattering at ``o`` for every given slot (all wait with ``FF = 2``): the NEE request (light
        sample, its weight; the slot's shadow ray starts), Russian roulette and the phase-sampled continuation.
        Uses lanes 2.. of the slot's current draw (:meth:`track` used lanes 0 and 1)."""
        lights = self.lights
        row = F.unbind(0)
        x, d, beta, csh, wi = row[0:3], row[3:6], row[8:11], row[21:24], row[15:18]
        n = I[_N]
        u = uniforms(I[_KEY], I[_CNT], self.lanes)
        zero = torch.zeros_like(row[_T])
        n_s = n + 1
        beta_s = tuple(b * self.albedo for b in beta)
        tse, sh = row[_TSE], I[_SH]
        lane = 4 + (self.rr_start is not None)
        if lights.n_lights:
            u_sel = u[lane] if lights.n_lights > 1 else zero
            lane += lights.n_lights > 1
            u_env = (u[lane], u[lane + 1]) if lights.env is not None else (zero, zero)
            wi, l_dist, l_w, l_pdf, l_env = lights.sample(x, u_sel, *u_env)
            tse = torch.minimum(box_exit(self.lo, self.hi, x, wi), l_dist)
            phase = hg_pdf(self.g, d[0] * wi[0] + d[1] * wi[1] + d[2] * wi[2])
            w = phase * torch.where(l_env, _power(l_pdf, phase), torch.ones_like(phase))
            csh = tuple(b * lw * w for b, lw in zip(beta_s, l_w))
            sh = torch.ones_like(sh)
        amax = torch.maximum(torch.maximum(beta_s[0], beta_s[1]), beta_s[2])
        stop = amax <= 0
        if not lights.has_env:
            stop = stop | (n_s >= self.max_scatter)
        if self.rr_start is not None:
            q = amax.clamp(0.05, 1.0)
            in_rr = n_s >= self.rr_start
            stop = stop | (in_rr & (u[4] >= q))
            beta_s = tuple(torch.where(in_rr, b / q, b) for b in beta_s)
        d_s, pdf_s = hg_sample3(self.g, d, u[2], u[3])
        t_far = box_exit(self.lo, self.hi, x, d_s)
        F = torch.stack([*x, *d_s, zero, t_far, *beta_s, pdf_s, *row[12:15], *wi, zero, tse, zero + 1.0, *csh])
        I = torch.stack([I[_PIX], I[_KEY], I[_CNT], n_s, (~stop).long(), sh, I[_OCC], I[_NSH]])
        return F, I


def camera_state(pt: PathTracer, sample_ids: Tensor) -> tuple[Tensor, Tensor]:
    """Fresh state columns ``(F (NF, N), I (NI, N))`` for camera sample ids ``(N,)`` (pixel ``id // spp``);
    the pixel jitter is the path's draw at counter 0."""
    cam, grid, dev = pt.scene.camera, pt.scene.grid, pt.device
    n = len(sample_ids)
    key = path_key(pt.scene.integrator.seed, sample_ids)
    pix = torch.div(sample_ids, pt.spp, rounding_mode="floor")
    o, d = cam.generate_rays(pix, torch.stack(uniforms(key, torch.zeros_like(key), 2), dim=1))
    t0, t1 = grid.box.intersect(o, d)
    F = torch.zeros(NF, n, device=dev)
    F[_O], F[_D], F[_T], F[_TMAX], F[_BETA] = o.T, d.T, t0, t1, 1.0
    I = torch.zeros(NI, n, dtype=torch.long, device=dev)
    I[_PIX], I[_KEY], I[_FF], I[_OCC] = pix, key, 1, 1
    return F, I


def inductor_cache_dir() -> Path:
    """The persistent compile cache: ``$TORCHINDUCTOR_CACHE_DIR``, set to ``~/.cache/nrc/inductor`` when unset."""
    default = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nrc" / "inductor"
    path = Path(os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(default)))
    path.mkdir(parents=True, exist_ok=True)
    return path


def multi_step(step: WavefrontStep, k: int) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """``k`` tracking steps as one function (one compiled graph); slots that reach a scattering vertex wait
    for :meth:`WavefrontStep.scatter` after the call."""

    def run(F: Tensor, I: Tensor) -> tuple[Tensor, Tensor]:
        for _ in range(k):
            F, I = step.track(F, I)
        return F, I

    return run


def render_loop(
    pt: PathTracer,
    machine: StateMachine,
    image: Tensor,
    timers: dict[str, float],
    counts: dict[str, int],
) -> None:
    """Drive ``machine`` over all camera samples, accumulating into ``image`` ``(H*W, 3)``. ``timers`` gets
    ``step`` (tracking), ``scatter`` and ``refill`` seconds, ``counts`` the work counters."""
    dev = pt.device
    total = pt.scene.camera.num_pixels * pt.spp
    S = max(min(pt.slots, total), 2)
    F = torch.zeros(NF, S, device=dev)
    I = torch.zeros(NI, S, dtype=torch.long, device=dev)
    next_id, calls = 0, 0
    while True:
        if calls % REFILL_EVERY == 0:
            t_rf = time.perf_counter()
            free = (I[_FF] == 0) & (I[_SH] == 0)
            idx = free.nonzero().squeeze(1)
            k = 0
            if len(idx):
                done = idx[I[_OCC, idx] != 0]
                if len(done):
                    image.index_add_(0, I[_PIX, done], F[_L, done].T)
                    counts["tracking_steps"] += int(I[_CNT, done].sum())
                    counts["shadow_steps"] += int(I[_NSH, done].sum())
                    if pt.lights.n_lights:
                        counts["shadow_rays"] += int(I[_N, done].sum())
                    I[_OCC, idx] = 0
                k = min(len(idx), total - next_id)
                if k:
                    slots = idx[:k]
                    Fn, In = camera_state(pt, torch.arange(next_id, next_id + k, device=dev))
                    F.index_copy_(1, slots, Fn)
                    I.index_copy_(1, slots, In)
                    next_id += k
            S = I.shape[1]
            live = S - len(idx) + k
            if live == 0:
                timers["refill"] += time.perf_counter() - t_rf
                return
            if next_id >= total and live < S // 2 and S > MIN_SLOTS:
                keep = (~free).nonzero().squeeze(1)
                if len(keep) < MIN_SLOTS:  # pad with idle slots
                    keep = torch.cat([keep, free.nonzero().squeeze(1)[: MIN_SLOTS - len(keep)]])
                F, I = F[:, keep].contiguous(), I[:, keep].contiguous()
            timers["refill"] += time.perf_counter() - t_rf
        t_st = time.perf_counter()
        F, I = machine.track(F, I)
        counts["iterations"] += 1
        calls += 1
        counts["slot_steps"] += I.shape[1] * pt.steps_per_call
        t_sc = time.perf_counter()
        timers["step"] += t_sc - t_st
        if calls % SCATTER_EVERY:
            continue
        sc = (I[_FF] == 2).nonzero().squeeze(1)
        if len(sc):
            counts["scatter_events"] += len(sc)
            Fs, Is = machine.scatter(F.index_select(1, sc), I.index_select(1, sc))
            F.index_copy_(1, sc, Fs)
            I.index_copy_(1, sc, Is)
        timers["scatter"] += time.perf_counter() - t_sc


def unsupported_reason(pt: PathTracer) -> str | None:
    """Why the compiled backend cannot render ``pt``'s configuration (``None``: it can)."""
    if pt.transmittance.name != "ratio":
        return f"transmittance {pt.transmittance.name!r} has no compiled kernel (only 'ratio')"
    if pt.lights.env_maps:
        return "lat-long environment maps have no compiled light sampler (directional, point, uniform sky only)"
    return None


def roulette_threshold(pt: PathTracer) -> float:
    """The ratio-tracking roulette threshold of ``pt``'s transmittance estimator (0 = off)."""
    return float(pt.transmittance.params.get("roulette_threshold", 0.1))


class StateMachine:
    """The functions of ``pt``'s state machine, compiled or run eagerly: ``track`` (``pt.steps_per_call``
    tracking steps of every slot) and ``scatter`` (the slots waiting at a scattering vertex).

    Args:
        pt: the path tracer (scene, lights, settings).
        compile: compile both with :func:`_compile` with the inductor cache
            under :func:`inductor_cache_dir`; ``False`` runs the identical code eagerly (tests).
    """

    def __init__(self, pt: PathTracer, compile: bool) -> None:
        bricks = BrickTables(pt.tracking_majorants, pt.majorants)
        step = WavefrontStep(pt.scene.grid, bricks, pt.lights, pt.scene.albedo, pt.scene.g, pt.max_scatter,
                             roulette_threshold(pt), pt.rr_start if pt.rr_enabled else None)
        track = multi_step(step, pt.steps_per_call)
        self._scatter_eager = step.scatter
        self.compiled = compile
        if compile:
            inductor_cache_dir()
            track, self._scatter = _compile(track), _compile(step.scatter)
        else:
            self._scatter = step.scatter
        self.track = track
        self.device = pt.device
        self.slots = max(pt.slots, MIN_SLOTS)
        self.startup_s: float | None = None

    def scatter(self, F: Tensor, I: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`WavefrontStep.scatter` (sizes below 2 run eagerly: dynamic shapes specialise them)."""
        return self._scatter(F, I) if F.shape[1] >= 2 else self._scatter_eager(F, I)

    def warm_up(self) -> float:
        """Compile (or load from the cache) by calls on an idle working set of full size (inductor picks
        its parallelisation from the sizes it sees first); returns the seconds it took (0 when already done)."""
        if self.startup_s is not None:
            return 0.0
        t0 = time.perf_counter()
        F = torch.zeros(NF, self.slots, device=self.device)
        I = torch.zeros(NI, self.slots, dtype=torch.long, device=self.device)
        self.track(F, I)
        k = max(self.slots // 16, 2)
        self.scatter(F[:, :k].contiguous(), I[:, :k].contiguous())
        self.startup_s = time.perf_counter() - t0
        return self.startup_s


MACHINE_CACHE = 4  # compiled state machines kept per process (one per scene and settings)
_machines: list[tuple[DensityGrid, tuple[Any, ...], StateMachine]] = []


def compiled_machine(pt: PathTracer) -> StateMachine:
    """The compiled state machine of ``pt``'s configuration, shared by every tracer of the same scene grid and
    settings in this process: a new :class:`~nrc.render.pt.PathTracer` for another spp count or seed (a
    reference chunk, a benchmark repeat) reuses it instead of re-tracing (seconds each). The grid is matched
    by identity, everything else the compiled code depends on by value."""
    lights = Lights3(pt.lights)
    key = (str(pt.device), pt.scene.grid.density_scale, pt.majorants.brick, pt.free_flight, lights.directional,
           lights.points, lights.env, pt.scene.albedo, pt.scene.g, pt.max_scatter, roulette_threshold(pt),
           pt.rr_start if pt.rr_enabled else None, pt.steps_per_call, max(pt.slots, MIN_SLOTS))
    for i, (grid, k, machine) in enumerate(_machines):
        if grid is pt.scene.grid and k == key:
            _machines.append(_machines.pop(i))
            return machine
    machine = StateMachine(pt, compile=True)
    _machines.append((pt.scene.grid, key, machine))
    del _machines[:-MACHINE_CACHE]
    return machine


StateFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]  # (F, I) -> (F, I)


def _compile(fn: StateFn) -> StateFn:
    """``torch.compile`` of a state function ``(F, I) -> (F, I)`` with a dynamic slot dimension (one graph for
    every size >= 2, no recompiles). Indices are clamped in the code: no bounds assertions in the gathers."""
    compiled = torch.compile(fn, dynamic=False, fullgraph=True, options={"assert_indirect_indexing": False})

    def run(F: Tensor, I: Tensor) -> tuple[Tensor, Tensor]:
        torch._dynamo.mark_dynamic(F, 1)
        torch._dynamo.mark_dynamic(I, 1)
        return compiled(F, I)

    return run


def render_state_machine(pt: PathTracer, machine: StateMachine, progress: bool = False) -> RenderResult:
    """Render ``pt``'s scene with ``machine``. ``time_render_s`` (and samples/s) exclude the start-up
    (compilation or cache load, reported as ``time_compile_s``)."""
    machine.warm_up()
    startup = machine.startup_s
    cam = pt.scene.camera
    total = cam.num_pixels * pt.spp
    image = torch.zeros(cam.num_pixels, 3, device=pt.device)
    timers = {"step": 0.0, "scatter": 0.0, "refill": 0.0}
    counts = {"tracking_steps": 0, "shadow_steps": 0, "shadow_rays": 0, "scatter_events": 0, "iterations": 0,
              "slot_steps": 0}
    start = time.perf_counter()
    render_loop(pt, machine, image, timers, counts)
    elapsed = time.perf_counter() - start
    img = (image / pt.spp).reshape(cam.height, cam.width, 3)
    if not bool(torch.isfinite(img).all()):
        raise RuntimeError("path tracer produced non-finite pixels")
    metrics: dict[str, Any] = {
        "renderer": pt.name,
        "backend": "compiled" if machine.compiled else "state_machine_eager",
        "free_flight": pt.free_flight,
        "brick": pt.majorants.brick,
        "transmittance": pt.transmittance.name,
        "spp": pt.spp,
        "samples": total,
        "slots": pt.slots,
        "steps_per_call": pt.steps_per_call,
        "time_compile_s": startup,
        "compile_cache_dir": os.environ.get("TORCHINDUCTOR_CACHE_DIR") if machine.compiled else None,
        "time_render_s": elapsed,
        "samples_per_second": total / elapsed if elapsed > 0 else math.inf,
        **{f"time_{k}_s": v for k, v in timers.items()},
        **counts,
    }
    return RenderResult(image=img.cpu().numpy(), metrics=metrics)
