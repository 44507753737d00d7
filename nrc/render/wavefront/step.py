"""The one transport step of the wavefront, shared by ``renderer=pt`` and ``renderer=nrc``.

Two pure functions of the packed state (:mod:`nrc.render.wavefront.state`) and the scene inputs, run either
eagerly or ``torch.compile``'d (the same code; :mod:`nrc.render.wavefront.machine`):

:meth:`Transport.track` -- one tracking step of every slot. A slot's pending shadow ray advances by one
    ratio-tracking step (its contribution lands in ``L`` when it ends) and, in the same step, its free flight
    takes one delta-tracking step against the majorant of the brick it is in (:meth:`BrickTables.segment`): a
    tentative collision inside the brick, a move to the brick's exit (an empty brick, and the empty cube around
    it, cost one step), or the end of the flight (``ESCAPED``; the environment is added when the slot is
    harvested). A real collision leaves the slot waiting at the vertex (``VERTEX``, ``o`` = the vertex) until the
    shadow ray of the vertex before it has ended, so a path's chain of steps is the longer of its flights and its
    shadow rays, not their sum; the continuation of the last allowed vertex that collides ends the path.
:meth:`Transport.vertex` -- the slots waiting at a real collision (a few percent; the driver runs it on that
    subset). The renderer's vertex program (:mod:`nrc.render.wavefront.program`) decides first: whether the path
    goes on (a path that ends here becomes a ``QUERY`` for the renderer), whether the vertex makes a next-event
    estimate and with which throughput and MIS, and whether the next segment's escape counts the environment.
    Then the step scatters: a next-event request (one light chosen by the light table, uniformly, by power or by
    resampling candidates (RIS); its shadow ray starts in the slot, or is queued for a transmittance estimator
    that has no per-step form), optional Russian roulette and the phase-sampled continuation.

Scene inputs are tensors, never Python constants: ``P`` (float32 ``(n_params,)``: box, grid dimensions,
density scale, albedo, g, limits, the brick tables' scalars, the lights' parameters; :meth:`Transport.params`),
the flat density grid and the flat majorant table. So a compiled step serves every scene, grid, camera and
light of the same *structure* (:attr:`Transport.key`: light types and counts, estimator, layout, settings that
change the code), and changing the density scale, g, albedo, a light or the VDB recompiles nothing.

:meth:`Transport.advance` -- the driver's tail (few live slots): :meth:`track`, then :meth:`vertex` on every slot
    that reached a vertex, in one call.

Random numbers are counter-based (:mod:`nrc.transport.rng`): the draw ``(key, cnt)`` of a path, lanes 0-1 for
the free flight's step, lanes 2.. for the vertex and the last two for the shadow ray's step, so an image depends
on ``(seed, path id)`` only, not on the number of slots, the refill cadence or which calls fuse the vertex.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.program import VertexProgram
from nrc.render.wavefront.state import DONE, ESCAPED, FLIGHT, QUERY, VERTEX, Layout, PathState, where3
from nrc.transport.light_sampling import LightSampler, LightTable, power_heuristic
from nrc.transport.phase import hg_pdf, hg_sample_v3
from nrc.transport.ris import resample
from nrc.transport.rng import uniforms as counter_uniforms
from nrc.transport.tracking import ratio_step
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
    def from_config(cls, renderer: Any) -> tuple[bool, RussianRoulette]:
        """``(enabled, rule)`` from the ``russian_roulette`` block of a :class:`nrc.config.ConfigReader` of the
        ``renderer`` block (every key required: the defaults live in ``conf/renderer/shared/wavefront.yaml``).
        Unknown keys of the block are errors."""
        rr = renderer.block("russian_roulette")
        enabled = rr.get_bool("enabled")
        rule = cls(rr.get_int("start", lo=1), rr.get_float("max_survival", lo=0.05, hi=1.0))
        rr.finish()
        return enabled, rule


@dataclass(frozen=True)
class StepOptions:
    """The core's own switches of a step's structure (the renderer's are in its vertex program)."""

    inline_shadow: bool
    """Shadow rays by ratio tracking inside the step; ``False`` queues them (``shadow = 2``) for the configured
    transmittance estimator."""
    roulette: bool
    """Ratio-tracking roulette on (its threshold is in ``P``)."""
    russian_roulette: bool
    """Throughput roulette on (its start and the survival cap ``q_max`` are in ``P``: a path from vertex ``start``
    on survives with ``q = clamp(max throughput, 0.05, q_max)``, weight ``1 / q``)."""


class Transport:
    """The step functions for one structure (see the module docstring).

    Args:
        program: the renderer's vertex program (its state fields, rows, ``P`` numbers, random lanes, decision).
        lights: the eager light sampler; its light table (structure; values in ``P``) is what the step samples,
            except for lat-long maps, which the eager step samples with the sampler itself.
        n_tables: brick tables (1, or 2 with global free flights).
        options: the core's switches (:class:`StepOptions`).
        uniforms: the random-number function ``(key, counter, lanes) -> lanes x (S,)`` (tests script it).
    """

    def __init__(self, program: VertexProgram, lights: LightSampler, n_tables: int, options: StepOptions,
                 uniforms: Uniforms = counter_uniforms) -> None:
        self.program = program
        self.lights = table = lights.table
        self.sampler = None if table.supported else lights
        # Decision.env_by_phase applies where the sky is the uniform one and a sample is a plain light sample (not
        # a resampled one): l_pdf is then P(select) / (4 pi) (lat-long maps and RIS keep light sampling alone)
        self.terminal_mis = table.supported and table.has_uniform_env and table.candidates == 1
        self.layout, self.n_tables = Layout.of(program), n_tables
        self.inline_shadow, self.roulette, self.rr = options.inline_shadow, options.roulette, options.russian_roulette
        self.uniforms = uniforms
        # vertex lanes: phase (2), then Russian roulette, the program's, the light choice
        self.lane_rr = 4
        self.lane_program = 4 + self.rr
        self.lane_light = self.lane_program + program.lanes
        m = table.candidates
        self.lanes = self.lane_light + (table.lanes if table.supported else 4 * m + (m > 1))
        names = ["lo", "lo", "lo", "hi", "hi", "hi", "dims", "dims", "dims", "scale", "albedo", "g", "max_scatter",
                 "roulette", "rr_start", *program.param_names]
        names += ["rr_q_max"] if self.rr else []
        self.ix: dict[str, int] = {}
        for k, name in enumerate(names):
            self.ix.setdefault(name, k)
        self.ix["bricks"] = len(names)
        self.ix["lights"] = len(names) + BrickTables.PER_TABLE * n_tables
        self.n_params = self.ix["lights"] + len(table.values)

    @property
    def fusable(self) -> bool:
        """The structure has the tail's fused step (:meth:`advance`): its shadow rays are traced inline and its
        vertex program lets the tail fuse its vertex (:attr:`VertexProgram.fused_tail`)."""
        return self.inline_shadow and self.program.fused_tail

    @property
    def structure(self) -> tuple[Any, ...]:
        """What the step's code depends on, as plain values (stable across processes; the persistent cache's
        marker is named from it)."""
        fn = self.uniforms
        return (self.program.structure, self.lights.structure, self.lights.supported, self.n_tables,
                self.inline_shadow, self.roulette, self.rr, f"{fn.__module__}.{fn.__qualname__}")

    @property
    def key(self) -> tuple[Any, ...]:
        """Everything the step's code depends on (scene numbers excluded): :attr:`structure`, the random-number
        function and, for lat-long maps, the eager sampler itself."""
        return (*self.structure, self.uniforms, id(self.sampler) if self.sampler else None)

    # ------------------------------------------------------------------ scene inputs
    def params(self, grid: Any, bricks: BrickTables, lights: LightTable, albedo: float, g: float,
               max_scatter: int, roulette_threshold: float, rr: RussianRoulette | None, **frame: Any) -> Tensor:
        """The scene's numbers as the step's ``P`` input (float32 on the grid's device; ``rr``: the throughput
        roulette's start and survival cap; ``frame``: the vertex program's numbers that change from frame to
        frame, :meth:`VertexProgram.param_values`)."""
        if lights.structure != self.lights.structure or bricks.n_tables != self.n_tables or \
                lights.supported != self.lights.supported:
            raise ValueError("scene structure differs from the step's")
        vals = [*grid.box.lo.tolist(), *grid.box.hi.tolist(), *[float(n) for n in grid.shape],
                float(grid.density_scale), float(albedo), float(g), float(max_scatter), float(roulette_threshold),
                float(rr.start if rr is not None else 0)]
        vals += [float(v) for v in self.program.param_values(**frame)]
        if self.rr:
            vals.append(float(rr.max_survival if rr is not None else 1.0))
        vals += bricks.values + lights.values
        return torch.tensor(vals, dtype=torch.float32, device=grid.device)

    def _vec(self, p: tuple[Tensor, ...], name: str) -> tuple[Tensor, Tensor, Tensor]:
        k = self.ix[name]
        return p[k], p[k + 1], p[k + 2]

    def row_of(self, s: PathState) -> Tensor | None:
        """Accumulator row ``(S,)`` that contributions of each slot's current segment go to (``None``: row 0)."""
        return self.program.row(s)

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
        # the draw (key, cnt): lanes 0-1 the free flight's step, the vertex's lanes after it (Transport.vertex, at the
        # counter of its collision), the last two the shadow ray's step (unused lanes are never computed compiled)
        u = self.uniforms(s.key, cnt, self.lanes + 2)
        zero = torch.zeros_like(s.t)
        inf = torch.full_like(s.t, math.inf)

        def tentative(o: tuple, d: tuple, t: Tensor, t_end: Tensor, shadow: bool, ud: Tensor, run: Tensor) -> tuple:
            """A delta-tracking step against the brick majorant: ``(majorant, hit, passed the end, x, t, sigma)``;
            the density is looked up only where a running ray's tentative collision needs it (the others read the
            box corner, whose voxels stay in cache)."""
            m, t_brick = BrickTables.segment(majorant, bricks, self.n_tables, o, d, t, shadow)
            seg_end = torch.minimum(t_brick, t_end)
            tc = torch.where(m > 0, t - torch.log1p(-ud) / m.clamp(min=1e-30), inf)
            hit = tc < seg_end
            tx = torch.where(hit, tc, seg_end)
            x = (o[0] + tx * d[0], o[1] + tx * d[1], o[2] + tx * d[2])
            sigma = scale * trilinear(density, dims, lo, hi, where3(hit & run, x, lo))
            return m, hit, ~hit & (seg_end >= t_end), x, tx, sigma

        # Shadow rays: ratio tracking (with roulette) from the vertex that started them (os), alongside the free
        # flight to the next vertex; the contribution lands in L when the ray ends.
        ms, hit_s, passed_s, _, txs, sigma_s = tentative(s.os, s.wi, s.ts, s.tse, True, u[-2], sh)
        Tn = torch.where(hit_s, ratio_step(s.tr, sigma_s, ms, u[-1], thr if self.roulette else None), s.tr)
        sh_end = sh & (passed_s | (Tn == 0))
        row = s.srow if s.srow is not None else self.row_of(s)  # the row its vertex chose
        gain = tuple(torch.where(sh_end, c * Tn, zero) for c in s.csh)
        s.L = self._add_to_rows(s.L, row, gain)
        s.ts = torch.where(sh, txs, s.ts)
        s.tr = torch.where(sh, Tn, s.tr)

        # Free flights: escape (the environment is added at harvest), null or real collision.
        m, hit, passed, x, tx, sigma = tentative(s.o, s.d, s.t, s.tmax, False, u[0], ff)
        esc = ff & passed
        real = ff & hit & (u[1] * m < sigma)
        s.t = torch.where(ff & ~passed & ~real, tx, s.t)
        at_limit = real & (s.n.to(torch.float32) >= max_scatter)  # the last vertex's continuation collided
        scat = real & ~at_limit
        s.o = where3(scat, x, s.o)
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

    # ------------------------------------------------------------------ the tail's fused step
    def advance(self, F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
        """One tracking step of every slot, then the vertex of every slot that reached one (the driver's tail:
        few live slots, where a call costs its fixed overhead, not its slots). The vertex runs on every slot and is
        kept where the slot waits at a real collision, so a path's draws and operations are those of
        :meth:`track` followed by a vertex pass. Only for inline shadow rays (a queued request needs the driver)."""
        F, I = self.track(F, I, P, density, majorant)
        at = (I[self.layout.i("flight")] == VERTEX) & (I[self.layout.i("shadow")] == 0)
        Fv, Iv = self.vertex(F, I, P, density, majorant)
        return torch.where(at, Fv, F), torch.where(at, Iv, I)

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
        prm = {name: p[self.ix[name]] for name in self.program.param_names}
        dec = self.program.decide(s, n_s, beta_s, albedo, prm, u[self.lane_program:self.lane_light])
        go, nee = dec.go, dec.nee
        lights = self.lights
        sh = torch.zeros_like(s.shadow)
        wi, tse, csh = s.wi, s.tse, s.csh
        d_s, pdf_s = hg_sample_v3(g, d, u[2], u[3])  # the continuation's direction (a terminal sky sample's too)
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
            by_phase = None
            if dec.env_by_phase is not None and self.terminal_mis:
                # a terminal vertex's uniform-sky sample: its direction by the sky or (here) by the phase function
                sky = l_env & ~dec.mis & ~go
                by_phase = sky & dec.env_by_phase
                wi = where3(by_phase, d_s, wi)
            tse = torch.minimum(box_exit(lo, hi, x, wi), l_dist)
            phase = phase_of(wi)
            # MIS against phase sampling where the path goes on to find the environment
            w = phase * torch.where(l_env & dec.mis, power_heuristic(l_pdf, phase), torch.ones_like(phase))
            if by_phase is not None:
                # one-sample MIS, balance heuristic, 1/2 each: L f / (P_sel (p_sky / 2 + f / 2)), and l_w = L / (P_sel
                # p_sky) with the uniform sky's p_sky = 1 / (4 pi): the phase factor becomes f / (1/2 + 2 pi f)
                w = torch.where(sky, phase / (0.5 + 2.0 * math.pi * phase), w)
            csh = tuple(b * lw * w for b, lw in zip(dec.nee_beta, l_w))
            sh = torch.where(nee, torch.full_like(sh, 1 if self.inline_shadow else 2), sh)
            s.n_shadow = s.n_shadow + (sh == 1).long()
        beta_s = dec.beta
        amax = torch.maximum(torch.maximum(beta_s[0], beta_s[1]), beta_s[2])
        stop = amax <= 0
        if not lights.has_env:  # the last vertex only continues when phase sampling can reach the sky (MIS)
            stop = stop | (n_s.to(torch.float32) >= max_scatter)
        if self.rr:
            q = torch.minimum(amax.clamp(0.05, 1.0), p[self.ix["rr_q_max"]])
            in_rr = n_s.to(torch.float32) >= p[self.ix["rr_start"]]
            stop = stop | (in_rr & (u[self.lane_rr] >= q))
            beta_s = tuple(torch.where(in_rr, b / q, b) for b in beta_s)
        t_far = box_exit(lo, hi, x, d_s)

        s.d = where3(go, d_s, d)
        s.t = torch.where(go, zero, s.t)
        s.tmax = torch.where(go, t_far, s.tmax)
        s.beta = where3(go, beta_s, s.beta)
        s.pdf = torch.where(go, pdf_s, s.pdf)
        if dec.skip_env is not None:
            if s.skip_env is None:
                raise TypeError(f"{type(self.program).__name__} sets Decision.skip_env but does not declare skips_env "
                                "(the state has no skip_env field)")
            s.skip_env = torch.where(go, dec.skip_env.long(), s.skip_env)
        s.wi = where3(nee, wi, s.wi)
        s.os = where3(nee, x, s.os)
        s.ts = torch.where(nee, zero, s.ts)
        s.tse = torch.where(nee, tse, s.tse)
        s.tr = torch.where(nee, zero + 1.0, s.tr)
        s.csh = where3(nee, csh, s.csh)
        s.n = torch.where(go, n_s, s.n)
        s.flight = torch.where(go, torch.where(stop, DONE, FLIGHT), torch.full_like(s.flight, QUERY))
        s.shadow = sh
        if s.srow is not None:  # several rows: the one this vertex's shadow ray adds to
            srow = dec.shadow_row if dec.shadow_row is not None else self.row_of(s)
            s.srow = torch.where(nee, srow, s.srow)
        return self.layout.pack(s)
