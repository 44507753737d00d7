"""The one transport step of the wavefront, shared by ``renderer=pt`` and ``renderer=nrc``.

Two pure functions of the packed state (:mod:`nrc.render.wavefront.state`) and the scene inputs, run either
eagerly or ``torch.compile``'d (the same code; :mod:`nrc.render.wavefront.machine`):

:meth:`Transport.track` -- one tracking step of every slot. A slot with a pending shadow ray advances it by
    one ratio-tracking step (its contribution lands in ``L`` when it ends); otherwise its free flight takes
    one delta-tracking step against the majorant of the brick it is in (:meth:`BrickTables.segment`): a
    tentative collision inside the brick, a move to the brick's exit (an empty brick costs one step), or the
    end of the flight (``ESCAPED``; the environment is added when the slot is harvested). A real collision
    leaves the slot waiting at the vertex (``VERTEX``, ``o`` = the vertex); the continuation of the last
    allowed vertex that collides ends the path.
:meth:`Transport.vertex` -- the slots waiting at a real collision (a few percent; the driver runs it on that
    subset). ``nrc`` first applies the termination rule: a terminating path becomes a cache query
    (``QUERY``), a training path records the vertex; with ``cache_target=indirect`` a terminating path still
    requests next-event estimation, weighted 1 (light sampling alone). Then both renderers scatter:
    throughput x albedo, a next-event request (one light chosen by the light table, uniformly, by power or by
    resampling candidates (RIS);
    its shadow ray starts in the slot, or is queued for a transmittance estimator that has no per-step form),
    optional Russian roulette and the phase-sampled continuation. With ``renderer.debias`` a render path that would
    terminate goes on with probability ``q`` instead (throughput ``/ q``, never terminating again), and the driver
    records its cache query with the weight ``beta (1 - 1/q)``: the cache becomes a control variate (module
    :mod:`nrc.render.radiance_caching.debias`).

Scene inputs are tensors, never Python constants: ``P`` (float32 ``(n_params,)``: box, grid dimensions,
density scale, albedo, g, limits, the brick tables' scalars, the lights' parameters; :meth:`Transport.params`),
the flat density grid and the flat majorant table. So a compiled step serves every scene, grid, camera and
light of the same *structure* (:attr:`Transport.key`: light types and counts, estimator, layout, settings that
change the code), and changing the density scale, g, albedo, a light or the VDB recompiles nothing.

Random numbers are counter-based (:mod:`nrc.transport.rng`): the draw ``(key, cnt)`` of a path, lanes 0-1 for
the tracking step and lanes 2.. for the vertex, so an image depends on ``(seed, path id)`` only, not on the
number of slots or the refill cadence.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.state import (CONTINUED, DONE, ESCAPED, FLIGHT, QUERY, VERTEX, Layout, PathState,
                                       accumulator_row)
from nrc.transport.light_sampling import LightSampler, LightTable, power_heuristic, resample
from nrc.transport.phase import hg_pdf, hg_sample_v3
from nrc.transport.rng import uniforms as counter_uniforms
from nrc.volume.box import box_exit
from nrc.volume.grid import trilinear
from nrc.volume.majorant import BrickTables

Uniforms = Callable[[Tensor, Tensor, int], list[Tensor]]


@dataclass(frozen=True)
class RussianRoulette:
    """The path tracer's throughput roulette (``renderer.russian_roulette``): from scattering event ``start`` on
    a path survives each vertex with ``q = min(clamp(max throughput, 0.05, 1), max_survival)`` and carries
    ``1 / q``. ``max_survival = 1`` never stops a path whose throughput stays near 1 (albedo 1); ``< 1`` (Mitsuba
    3's rule uses 0.95) bounds a path's expected length after ``start`` by ``1 / (1 - max_survival)`` vertices,
    at the price of weights that grow as ``max_survival^-n``."""

    start: int
    max_survival: float = 1.0

    @classmethod
    def from_config(cls, renderer: Any, defaults: bool = False) -> tuple[bool, RussianRoulette]:
        """``(enabled, rule)`` from the ``russian_roulette`` block of a :class:`nrc.config.ConfigReader` of the
        ``renderer`` block (``defaults``: missing keys take off, vertex 8 and this class's cap; otherwise they are
        required, their defaults living in the YAML). Unknown keys of the block are errors."""
        rr = renderer.block("russian_roulette")

        def default(value: Any) -> tuple:
            return (value,) if defaults else ()

        enabled = rr.get_bool("enabled", *default(False))
        rule = cls(rr.get_int("start", *default(8), lo=1),
                   rr.get_float("max_survival", *default(cls.max_survival), lo=0.05, hi=1.0))
        rr.finish()
        return enabled, rule


@dataclass(frozen=True)
class NRCRule:
    """What the ``nrc`` vertex needs of the termination rule and the training set (structure only; the
    numbers travel in ``P``)."""

    rule: str  # "count" | "spread"
    records_per_path: int  # V
    # "full": the cache holds all scattered radiance, a terminating path does no next-event estimation;
    # "indirect": the cache holds the scattered radiance minus the direct light, and a terminating path adds
    # next-event estimation by light sampling alone (no MIS: nothing continues to pick up its other half)
    cache_target: str = "full"
    # renderer.debias (nrc.render.radiance_caching.debias): a render path that would terminate into the cache goes
    # on instead, with probability q (P's debias_q), as a path-traced suffix of throughput beta / q that never
    # terminates again (never = CONTINUED); the driver queries the cache there with weight beta (1 - 1/q)
    debias: bool = False


def _where3(m: Tensor, a: tuple, b: tuple) -> tuple:
    return tuple(torch.where(m, x, y) for x, y in zip(a, b))


class Transport:
    """The step functions for one structure (see the module docstring).

    Args:
        layout: the state layout (``rows`` accumulator rows; NRC fields).
        lights: the light table (structure; its values go into ``P``).
        n_tables: brick tables (1, or 2 with global free flights).
        inline_shadow: shadow rays by ratio tracking inside the step; ``False`` queues them (``shadow = 2``)
            for the configured transmittance estimator.
        roulette: ratio-tracking roulette on (its threshold is in ``P``).
        russian_roulette: throughput roulette on (its start and the survival cap ``q_max`` are in ``P``: a path
            from vertex ``start`` on survives with ``q = clamp(max throughput, 0.05, q_max)``, weight ``1 / q``).
        nrc: the termination rule and ``V`` for ``renderer=nrc``, ``None`` for ``pt``.
        uniforms: the random-number function ``(key, counter, lanes) -> lanes x (S,)`` (tests script it).
    """

    def __init__(self, layout: Layout, lights: LightTable, n_tables: int, inline_shadow: bool, roulette: bool,
                 russian_roulette: bool, nrc: NRCRule | None = None, uniforms: Uniforms = counter_uniforms,
                 sampler: LightSampler | None = None, reuse_vertex: int = 0, reuse_light_only: bool = False) -> None:
        if not lights.supported and sampler is None:
            raise ValueError("lat-long environment maps need the eager light sampler (sampler=)")
        self.sampler = None if lights.supported else sampler
        self.layout, self.lights, self.n_tables = layout, lights, n_tables
        self.inline_shadow, self.roulette, self.rr, self.nrc = inline_shadow, roulette, russian_roulette, nrc
        self.uniforms = uniforms
        # reservoir reuse (nrc.render.wavefront.reuse): render paths' vertex reuse_vertex (0: none) leaves its
        # next-event estimate to the reuse pass, which the driver records the vertex for
        self.reuse_vertex = int(reuse_vertex)
        # reuse.domain=distance: the reuse pass estimates all of that vertex's direct light by light sampling, so the
        # path's phase-sampled direction from it does not count the environment it reaches
        self.reuse_light_only = bool(reuse_light_only) and self.reuse_vertex > 0
        # vertex lanes: phase (2), then Russian roulette, the termination draw (nrc), the debias draw (nrc with
        # renderer.debias), the light choice
        self.lane_rr = 4
        self.lane_term = 4 + russian_roulette
        self.debias = nrc is not None and nrc.debias
        self.lane_debias = self.lane_term + (nrc is not None)
        self.lane_light = self.lane_debias + self.debias
        self.indirect_debias = self.debias and nrc.cache_target == "indirect"
        m = lights.candidates
        self.lanes = self.lane_light + (lights.lanes if lights.supported else 4 * m + (m > 1))
        names = ["lo", "lo", "lo", "hi", "hi", "hi", "dims", "dims", "dims", "scale", "albedo", "g", "max_scatter",
                 "roulette", "rr_start", "min_vertices", "p_continue", "spread_c", "unbiased_cap"]
        names += ["debias_q"] if self.debias else []
        names += ["rr_q_max"] if self.rr else []
        self.ix: dict[str, int] = {}
        for k, name in enumerate(names):
            self.ix.setdefault(name, k)
        self.ix["bricks"] = len(names)
        self.ix["lights"] = len(names) + BrickTables.PER_TABLE * n_tables
        self.n_params = self.ix["lights"] + len(lights.values)

    @property
    def structure(self) -> tuple[Any, ...]:
        """What the step's code depends on, as plain values (stable across processes; the persistent cache's
        marker is named from it)."""
        fn = self.uniforms
        base = (self.layout.rows, self.layout.nrc, self.lights.structure, self.lights.supported, self.n_tables,
                self.inline_shadow, self.roulette, self.rr, self.nrc, f"{fn.__module__}.{fn.__qualname__}")
        if not self.reuse_vertex:
            return base
        return (*base, ("reuse", self.reuse_vertex, "light_only") if self.reuse_light_only else ("reuse", self.reuse_vertex))

    @property
    def key(self) -> tuple[Any, ...]:
        """Everything the step's code depends on (scene numbers excluded): :attr:`structure`, the random-number
        function and, for lat-long maps, the eager sampler itself."""
        return (*self.structure, self.uniforms, id(self.sampler) if self.sampler else None)

    # ------------------------------------------------------------------ scene inputs
    def params(self, grid: Any, bricks: BrickTables, lights: LightTable, albedo: float, g: float,
               max_scatter: int, roulette_threshold: float, rr: RussianRoulette | None,
               termination: Any = None, debias_q: float = 0.0, unbiased_cap: int = 0) -> Tensor:
        """The scene's numbers as the step's ``P`` input (float32 on the grid's device; ``rr``: the throughput
        roulette's start and survival cap; ``debias_q``: the probability that a render path goes on past its cache
        termination, with ``renderer.debias``; ``unbiased_cap``: the vertex at which an unbiased training path
        terminates into the cache after all, 0 for never)."""
        if lights.structure != self.lights.structure or bricks.n_tables != self.n_tables or \
                lights.supported != self.lights.supported:
            raise ValueError("scene structure differs from the step's")
        vals = [*grid.box.lo.tolist(), *grid.box.hi.tolist(), *[float(n) for n in grid.shape],
                float(grid.density_scale), float(albedo), float(g), float(max_scatter), float(roulette_threshold),
                float(rr.start if rr is not None else 0)]
        if termination is not None:
            vals += [float(termination.min_vertices), float(termination.p_continue), float(termination.spread_c)]
        else:
            vals += [0.0, 0.0, 0.0]
        vals.append(float(unbiased_cap))
        if self.debias:
            vals.append(float(debias_q))
        if self.rr:
            vals.append(float(rr.max_survival if rr is not None else 1.0))
        vals += bricks.values + lights.values
        return torch.tensor(vals, dtype=torch.float32, device=grid.device)

    def _vec(self, p: tuple[Tensor, ...], name: str) -> tuple[Tensor, Tensor, Tensor]:
        k = self.ix[name]
        return p[k], p[k + 1], p[k + 2]

    def row_of(self, s: PathState) -> Tensor | None:
        """Accumulator row ``(S,)`` that contributions of each slot's current segment go to (``None``: row 0)."""
        if self.layout.rows == 1:
            return None
        return accumulator_row(s.rec_base, s.n, self.layout.rows - 1, s.never if self.debias else None)

    # ------------------------------------------------------------------ one tracking step
    def track(self, F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
        """One tracking step of every slot (see the module docstring)."""
        s = self.layout.unpack(F, I)
        p = P.unbind(0)
        lo, hi, dims = self._vec(p, "lo"), self._vec(p, "hi"), self._vec(p, "dims")
        scale, max_scatter, thr = p[self.ix["scale"]], p[self.ix["max_scatter"]], p[self.ix["roulette"]]
        bricks = list(p[self.ix["bricks"]:self.ix["lights"]])

        ff, sh = s.flight == FLIGHT, s.shadow == 1
        cnt = s.cnt + (ff | sh).long()
        u0, u1 = self.uniforms(s.key, cnt, 2)
        zero = torch.zeros_like(s.t)

        run_ff = ff & ~sh
        dr = _where3(sh, s.wi, s.d)
        tr = torch.where(sh, s.ts, s.t)
        te = torch.where(sh, s.tse, s.tmax)
        m, t_brick = BrickTables.segment(majorant, bricks, self.n_tables, s.o, dr, tr, sh)
        seg_end = torch.minimum(t_brick, te)
        tc = torch.where(m > 0, tr - torch.log1p(-u0) / m.clamp(min=1e-30), torch.full_like(tr, math.inf))
        hit = tc < seg_end
        passed = ~hit & (seg_end >= te)
        tx = torch.where(hit, tc, seg_end)
        x = (s.o[0] + tx * dr[0], s.o[1] + tx * dr[1], s.o[2] + tx * dr[2])
        # Only tentative collisions of running rays need the density; the others look up the box corner,
        # whose voxels stay in cache (a brick crossing or an idle slot costs no memory traffic).
        need = hit & (run_ff | sh)
        sigma = scale * trilinear(density, dims, lo, hi, _where3(need, x, lo))
        nul = (1.0 - sigma / m.clamp(min=1e-30)).clamp(min=0.0)

        # Shadow rays: ratio tracking (with roulette); the contribution lands in L when the ray ends.
        Tn = torch.where(hit, s.tr * nul, s.tr)
        if self.roulette:
            Tn = torch.where(hit & (Tn < thr), (u1 < Tn).to(Tn.dtype), Tn)
        sh_end = sh & (passed | (Tn == 0))
        row = self.row_of(s)
        gain = tuple(torch.where(sh_end, c * Tn, zero) for c in s.csh)
        s.L = self._add_to_rows(s.L, row, gain)
        s.ts = torch.where(sh, tx, s.ts)
        s.tr = torch.where(sh, Tn, s.tr)

        # Free flights: escape (the environment is added at harvest), null or real collision.
        esc = run_ff & passed
        real = run_ff & hit & (u1 * m < sigma)
        s.t = torch.where(run_ff & ~passed & ~real, tx, s.t)
        at_limit = real & (s.n.to(torch.float32) >= max_scatter)  # the last vertex's continuation collided
        scat = real & ~at_limit
        s.o = _where3(scat, x, s.o)
        s.flight = torch.where(scat, VERTEX, torch.where(esc, ESCAPED, torch.where(at_limit, DONE, s.flight)))
        s.shadow = (sh & ~sh_end).long()
        s.n_shadow_steps = s.n_shadow_steps + sh.long()
        s.cnt = cnt
        return self.layout.pack(s)

    def _add_to_rows(self, L: tuple, row: Tensor | None, gain: tuple) -> tuple:
        if row is None:
            return (tuple(a + b for a, b in zip(L[0], gain)),)
        out = []
        for j, Lj in enumerate(L):
            m = row == j
            out.append(tuple(a + torch.where(m, b, torch.zeros_like(b)) for a, b in zip(Lj, gain)))
        return tuple(out)

    # ------------------------------------------------------------------ a real collision
    def vertex(self, F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
        """Every given slot waits at a real collision (``VERTEX``): terminate (``nrc``) or scatter."""
        s = self.layout.unpack(F, I)
        p = P.unbind(0)
        lo, hi = self._vec(p, "lo"), self._vec(p, "hi")
        albedo, g, max_scatter = p[self.ix["albedo"]], p[self.ix["g"]], p[self.ix["max_scatter"]]
        u = self.uniforms(s.key, s.cnt, self.lanes)
        x, d = s.o, s.d
        zero = torch.zeros_like(s.t)
        n_s = s.n + 1
        beta_s = tuple(b * albedo for b in s.beta)
        go = torch.ones_like(s.n, dtype=torch.bool)  # the path scatters here (nrc: it does not terminate)
        cont = torch.zeros_like(go)  # renderer.debias: a render path goes on past its cache termination here

        if self.nrc is not None:
            V = self.nrc.records_per_path
            # the termination rule at vertex n_s (termination.py)
            dist2 = sum((xa - pa) ** 2 for xa, pa in zip(x, s.x_prev))
            first = n_s == 1
            a0 = torch.where(first, dist2 / (4.0 * math.pi), s.a0)
            spread = torch.where(first, zero, s.spread + torch.sqrt(dist2 / s.pdf.abs().clamp(min=1e-30)))
            eligible = n_s.to(torch.float32) >= p[self.ix["min_vertices"]]
            if self.nrc.rule == "count":
                fire = eligible & (u[self.lane_term] >= p[self.ix["p_continue"]])
            else:
                fire = eligible & (spread * spread > p[self.ix["spread_c"]] * a0)
            n_term = torch.where(fire & (s.n_term == 0) & (s.never == 0), n_s + s.extra, s.n_term)
            # renderer.training.unbiased_max_vertices: an unbiased training path ends in the cache at that vertex
            cap = p[self.ix["unbiased_cap"]]
            capped = (s.never == 1) & (cap > 0) & (n_s.to(torch.float32) >= cap)
            n_term = torch.where(capped & (n_term == 0), n_s, n_term)
            terminate = (n_term > 0) & (n_s >= n_term)
            is_train = s.rec_base >= 0
            if self.debias:  # with probability q the render path goes on as a path-traced suffix
                cont = terminate & ~is_train & (u[self.lane_debias] < p[self.ix["debias_q"]])
                terminate = terminate & ~cont
                n_term = torch.where(cont, torch.zeros_like(n_term), n_term)
                s.never = torch.where(cont, torch.full_like(s.never, CONTINUED), s.never)
            go = ~terminate
            recorded = go & is_train & (n_s <= V)
            beta_s = tuple(torch.where(recorded, albedo + zero, b) for b in beta_s)
            s.rec = torch.where(recorded, s.rec_base + n_s - 1, torch.full_like(s.rec, -1))
            s.spread, s.a0, s.n_term = spread, a0, n_term
            s.x_prev = _where3(go, x, s.x_prev)

        # the vertex does next-event estimation: a scattering one; with cache_target=indirect a terminating one too
        nee = go if self.nrc is None or self.nrc.cache_target == "full" else torch.ones_like(go)
        at = None
        if self.reuse_vertex:  # a render path's reuse vertex: its next-event estimate is the reuse pass's
            at = n_s == self.reuse_vertex
            at = at if self.nrc is None else at & (s.rec_base < 0)
            nee = nee & ~at
        lights = self.lights
        sh = torch.zeros_like(s.shadow)
        wi, tse, csh = s.wi, s.tse, s.csh
        if lights.n_lights:
            def phase_of(w: tuple) -> Tensor:
                return hg_pdf(g, d[0] * w[0] + d[1] * w[1] + d[2] * w[2])

            ul = u[self.lane_light:self.lanes]
            if self.sampler is None:
                lv = list(p[self.ix["lights"]:self.n_params])
                wi, l_dist, l_w, l_pdf, l_env = lights.sample_ris(lv, x, ul, phase_of)
            else:  # lat-long maps: the eager sampler (this structure runs eagerly only)
                def draw(uu: list) -> tuple:
                    ls = self.sampler.sample(torch.stack(x, 1), torch.stack(uu, 1))
                    return tuple(ls.wi.unbind(1)), ls.distance, tuple(ls.weight.unbind(1)), ls.light_pdf, ls.is_env

                m = lights.candidates
                cands = [draw(ul[4 * j:4 * j + 4]) for j in range(m)]
                wi, l_dist, l_w, l_pdf, l_env = cands[0] if m == 1 else resample(cands, phase_of, ul[4 * m])[0]
            tse = torch.minimum(box_exit(lo, hi, x, wi), l_dist)
            phase = phase_of(wi)
            # MIS against phase sampling where the path goes on to find the environment; a continued path under
            # cache_target=indirect keeps the terminal vertex's estimate (light sampling alone, throughput beta)
            mis = go & ~cont if self.indirect_debias else go
            w = phase * torch.where(l_env & mis, power_heuristic(l_pdf, phase), torch.ones_like(phase))
            b_nee = beta_s
            if self.debias and not self.indirect_debias:  # full: the vertex's estimate is part of the suffix
                b_nee = tuple(torch.where(cont, b / p[self.ix["debias_q"]], b) for b in beta_s)
            csh = tuple(b * lw * w for b, lw in zip(b_nee, l_w))
            sh = torch.where(nee, torch.full_like(sh, 1 if self.inline_shadow else 2), sh)
        if self.debias:  # the suffix carries 1/q
            beta_s = tuple(torch.where(cont, b / p[self.ix["debias_q"]], b) for b in beta_s)
        amax = torch.maximum(torch.maximum(beta_s[0], beta_s[1]), beta_s[2])
        stop = amax <= 0
        if not lights.has_env:  # the last vertex only continues when phase sampling can reach the sky (MIS)
            stop = stop | (n_s.to(torch.float32) >= max_scatter)
        if self.rr:
            q = torch.minimum(amax.clamp(0.05, 1.0), p[self.ix["rr_q_max"]])
            in_rr = n_s.to(torch.float32) >= p[self.ix["rr_start"]]
            stop = stop | (in_rr & (u[self.lane_rr] >= q))
            beta_s = tuple(torch.where(in_rr, b / q, b) for b in beta_s)
        d_s, pdf_s = hg_sample_v3(g, d, u[2], u[3])
        t_far = box_exit(lo, hi, x, d_s)

        s.d = _where3(go, d_s, d)
        s.t = torch.where(go, zero, s.t)
        s.tmax = torch.where(go, t_far, s.tmax)
        s.beta = _where3(go, beta_s, s.beta)
        # pdf < 0 marks a segment whose environment is not counted at the escape: a continued path's first segment
        # under cache_target=indirect (its vertex's direct light came from light sampling alone)
        # (and, with reuse_light_only, a render path's segment from its reuse vertex)
        no_env = cont if self.indirect_debias else None
        if self.reuse_light_only:
            no_env = at if no_env is None else no_env | at
        s.pdf = torch.where(go, torch.where(no_env, -pdf_s, pdf_s) if no_env is not None else pdf_s, s.pdf)
        s.wi = _where3(nee, wi, s.wi)
        s.ts = torch.where(nee, zero, s.ts)
        s.tse = torch.where(nee, tse, s.tse)
        s.tr = torch.where(nee, zero + 1.0, s.tr)
        s.csh = _where3(nee, csh, s.csh)
        s.n = torch.where(go, n_s, s.n)
        s.flight = torch.where(go, torch.where(stop, DONE, FLIGHT), torch.full_like(s.flight, QUERY))
        s.shadow = sh
        return self.layout.pack(s)
