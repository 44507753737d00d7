"""``renderer=nrc`` at a vertex: its vertex program (inside the transport step) and its collector (the driver).

The program (:class:`NRCVertex`, part of the compiled step) applies the termination rule
(:mod:`~nrc.render.radiance_caching.termination`), decides which training records a vertex writes, and, with
``renderer.debias``, lets a render path that would terminate go on with probability ``q`` as a path-traced suffix
(throughput ``/ q``, never terminating again: ``never = CONTINUED``). With ``cache_target=indirect`` a
terminating vertex still makes its next-event estimate: by light sampling, except that a sample of the uniform sky
draws its direction by the sky or by the phase function, 1/2 each (``renderer.terminal_nee=mis``: one-sample MIS, the
balance heuristic; the path does not go on to find the sky by phase sampling, and the sky's own uniform directions
weighted by a forward-peaked phase function are fireflies), or by light sampling alone (``terminal_nee=light``).

The collector (:class:`NRCCollector`) maps each slot's contributions to the accumulator rows of
:mod:`~nrc.render.radiance_caching.paths` (pixel, training records, the records' direct light, the debias
suffix rows), collects the cache queries of harvested slots and of continued paths (weight ``beta (1 - 1/q)``),
and writes the training records' positions and directions.

State fields (besides the core's, :mod:`nrc.render.wavefront.state`):

============ ===== =====================================================================================
``spread``   1     path spread of the ``spread`` termination rule
``a0``       1     spread at the first vertex
``x_prev``   3     previous vertex (the camera at first)
``d_in``     3     incoming direction at the last vertex that wrote a training record (the record's direction)
============ ===== =====================================================================================

Integer fields: ``pid`` (path id), ``rec_base`` (first training record of a training path, -1 for render paths),
``n_term`` (vertex at which the path terminates into the cache, 0 undecided), ``extra`` (vertices past the render
stop), ``never`` (never terminates: 1 a training path's unbiased suffix, :data:`CONTINUED` a render path that would
have terminated into the cache and goes on as a path-traced suffix, ``renderer.debias``), ``rec`` (training record
written at the last vertex, -1 none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.program import Collector, Decision, VertexEvent, VertexProgram
from nrc.render.wavefront.state import QUERY, VERTEX, where3

# ``never`` of a render path continued past its cache termination (renderer.debias): its contributions from there
# on go to accumulator row 1, the suffix row (the collector maps it to the sample's own row of the accumulator)
CONTINUED = 2


def just_continued(never_before: Tensor, never_after: Tensor) -> Tensor:
    """Slots whose render path the vertex step between the two ``never`` values continued past its cache
    termination (:data:`CONTINUED`, ``renderer.debias``)."""
    return (never_after == CONTINUED) & (never_before != CONTINUED)


def accumulator_row(rec_base: Tensor, n: Tensor, V: int, never: Tensor | None = None) -> Tensor:
    """Accumulator row ``(S,)`` of each slot's current segment: a training path's ``min(n, V)`` (row 0 is its
    discard row before the first vertex); for a render path 0 (its ``dest``), or 1 (its suffix row) once it is
    :data:`CONTINUED` past its cache termination (``never`` given: ``renderer.debias``)."""
    render = torch.zeros_like(n) if never is None else (never == CONTINUED).long()
    return torch.where(rec_base >= 0, n.clamp(max=V), render)


class NRCVertex(VertexProgram):
    """The NRC vertex (module docstring) of the renderer's settings (:class:`~nrc.render.radiance_caching.settings.
    NRCSettings`, passed whole). Structure: the termination rule (``count`` | ``spread``), ``records_per_path`` (V),
    ``cache_target`` (``full`` | ``indirect``), ``debias`` on; numbers (the rule's, ``unbiased_max_vertices``: the
    vertex at which an unbiased training path ends in the cache after all, 0 never; per frame ``debias_q``) go into
    ``P`` only."""

    float_fields = (("spread", 1), ("a0", 1), ("x_prev", 3), ("d_in", 3))
    int_fields = ("pid", "rec_base", "n_term", "extra", "never", "rec")

    def __init__(self, settings: Any, hooks: tuple = ()) -> None:
        super().__init__(hooks)
        st = settings
        self.rule, self.V, self.cache_target = st.termination.rule, int(st.training.records_per_path), st.cache_target
        self.debias = bool(st.debias.enabled)
        self.termination, self.unbiased_cap = st.termination, int(st.training.unbiased_max_vertices)
        # accumulator rows of a slot's L: 0 (the pixel, a training path's discard row, or with debias a continued
        # path's suffix row 1), the V records, and with cache_target=indirect the V records' own direct light
        self.rows = 1 + self.V + (self.V if self.cache_target == "indirect" else 0)
        # renderer.terminal_nee=mis: a terminating vertex's sky sample by the sky or the phase function (Decision)
        self.terminal_mis = self.cache_target == "indirect" and st.terminal_nee == "mis"
        self.lanes = 1 + self.debias + self.terminal_mis  # the termination draw, the debias draw, the sky's strategy
        self.param_names = ("min_vertices", "p_continue", "spread_c", "unbiased_cap") + (
            ("debias_q",) if self.debias else ())
        # a continued path under cache_target=indirect keeps the terminal vertex's estimate (light sampling alone)
        self.indirect_debias = self.debias and self.cache_target == "indirect"

    @property
    def fused_tail(self) -> bool:
        """The tail may fuse the vertex: a training record's position (``o``) and direction (``d_in``) stay in the
        slot until its next vertex, where the collector reads them after each fused call. Not with ``debias`` (its
        control-variate queries need the throughput before the vertex) or hooks (their watchers need the passes)."""
        return not self.debias and not self.hooks

    @property
    def own_skips_env(self) -> bool:  # a continued path's next segment does not count the sky (indirect debias)
        return self.indirect_debias

    @property
    def structure(self) -> tuple[Any, ...]:
        return ("nrc", self.rule, self.V, self.cache_target, self.debias, self.terminal_mis,
                *(h.structure for h in self.hooks))

    def param_values(self, debias_q: float = 0.0, **frame: Any) -> list[float]:
        t = self.termination
        vals = [t.min_vertices, t.p_continue, t.spread_c, self.unbiased_cap]
        return vals + ([debias_q] if self.debias else [])

    def row(self, s: Any) -> Tensor:
        return accumulator_row(s.rec_base, s.n, self.V, s.never if self.debias else None)

    def render_path(self, s: Any) -> Tensor:
        return s.rec_base < 0

    def at_vertex(self, s: Any, n_s: Tensor, beta_s: tuple, albedo: Tensor, prm: dict[str, Tensor],
                  u: list[Tensor]) -> Decision:
        x, V = s.o, self.V
        zero = torch.zeros_like(s.t)
        cont = torch.zeros_like(n_s, dtype=torch.bool)  # renderer.debias: goes on past its cache termination here
        # the termination rule at vertex n_s (termination.py)
        dist2 = sum((xa - pa) ** 2 for xa, pa in zip(x, s.x_prev))
        first = n_s == 1
        a0 = torch.where(first, dist2 / (4.0 * math.pi), s.a0)
        spread = torch.where(first, zero, s.spread + torch.sqrt(dist2 / s.pdf.clamp(min=1e-30)))
        eligible = n_s.to(torch.float32) >= prm["min_vertices"]
        if self.rule == "count":
            fire = eligible & (u[0] >= prm["p_continue"])
        else:
            fire = eligible & (spread * spread > prm["spread_c"] * a0)
        n_term = torch.where(fire & (s.n_term == 0) & (s.never == 0), n_s + s.extra, s.n_term)
        # renderer.training.unbiased_max_vertices: an unbiased training path ends in the cache at that vertex
        cap = prm["unbiased_cap"]
        capped = (s.never == 1) & (cap > 0) & (n_s.to(torch.float32) >= cap)
        n_term = torch.where(capped & (n_term == 0), n_s, n_term)
        terminate = (n_term > 0) & (n_s >= n_term)
        is_train = s.rec_base >= 0
        if self.debias:  # with probability q the render path goes on as a path-traced suffix
            cont = terminate & ~is_train & (u[1] < prm["debias_q"])
            terminate = terminate & ~cont
            n_term = torch.where(cont, torch.zeros_like(n_term), n_term)
            s.never = torch.where(cont, torch.full_like(s.never, CONTINUED), s.never)
        go = ~terminate
        recorded = go & is_train & (n_s <= V)
        beta_s = tuple(torch.where(recorded, albedo + zero, b) for b in beta_s)
        s.rec = torch.where(recorded, s.rec_base + n_s - 1, torch.full_like(s.rec, -1))
        s.d_in = where3(recorded, s.d, s.d_in)  # the record's direction: the incoming one, before the scattering
        s.spread, s.a0, s.n_term = spread, a0, n_term
        s.x_prev = where3(go, x, s.x_prev)
        # the vertex does next-event estimation: a scattering one; with cache_target=indirect a terminating one too
        nee = go if self.cache_target == "full" else torch.ones_like(go)
        mis = go & ~cont if self.indirect_debias else go
        nee_beta, beta = beta_s, beta_s
        if self.debias:  # the suffix carries 1/q (under full, the vertex's estimate is part of it)
            q = prm["debias_q"]
            if not self.indirect_debias:
                nee_beta = tuple(torch.where(cont, b / q, b) for b in beta_s)
            beta = tuple(torch.where(cont, b / q, b) for b in beta_s)
        # the row of the vertex's shadow ray: the record's direct-light row where a record is written under
        # cache_target=indirect, the pixel for a continued vertex's own estimate (indirect debias), else the row of
        # the segment the vertex starts
        n_new = torch.where(go, n_s, s.n)
        shadow_row = accumulator_row(s.rec_base, n_new, V, s.never if self.debias else None)
        if self.cache_target == "indirect":
            shadow_row = torch.where(s.rec >= 0, V + n_s, shadow_row)
            if self.indirect_debias:
                shadow_row = torch.where(cont, torch.zeros_like(shadow_row), shadow_row)
        # a continued path's first segment under cache_target=indirect does not count the environment: its
        # vertex's direct light came from light sampling alone
        # renderer.terminal_nee=mis: the sky's strategy, 1/2 each (the step applies it to terminal sky samples)
        env_by_phase = u[1 + self.debias] < 0.5 if self.terminal_mis else None
        return Decision(go=go, nee=nee, mis=mis, nee_beta=nee_beta, beta=beta,
                        skip_env=cont if self.indirect_debias else None, shadow_row=shadow_row,
                        env_by_phase=env_by_phase)


@dataclass
class NRCCollector(Collector):
    """What ``nrc`` collects besides the accumulator (rows: :mod:`~nrc.render.radiance_caching.paths`)."""

    n_pixels: int
    n_render: int
    V: int
    rec_x: Tensor  # (pool paths * V, 3) training-record positions, written at recorded vertices (TrainingPool)
    rec_d: Tensor
    rec_valid: Tensor
    scattered: Tensor  # (pool paths,) bool
    # cache_target=indirect: accumulator row of record 0's direct light (next-event estimate and MIS-weighted
    # environment of a recorded vertex go to direct_base + record instead of the record's row); None: full
    direct_base: int | None = None
    queries: dict[str, list[Tensor]] = field(
        default_factory=lambda: {k: [] for k in ("x", "d", "w", "dest", "pid", "cont")})
    # renderer.debias: the probability q of going on past a cache termination (0: off); accumulator row of render
    # sample 0's suffix (a continued path's contributions from its terminal vertex on, sample k's at
    # suffix_base + k); the continued paths' (sample id, throughput beta at the vertex), in the order of their
    # queries, which are the ones flagged in queries["cont"]
    debias_q: float = 0.0
    suffix_base: int | None = None
    continued: dict[str, list[Tensor]] = field(default_factory=lambda: {"pid": [], "beta": []})
    watchers: tuple = ()  # objects with record(VertexEvent) (the reuse pass's vertex record)
    finished: Tensor | None = None  # (pool paths,) bool: set for the training paths harvested (their records complete)

    def __post_init__(self) -> None:
        self.watchers = tuple(w for w in self.watchers if w is not None)

    @property
    def needs_vertex_passes(self) -> bool:
        """With ``renderer.debias`` the continued paths' control-variate queries, and a watcher's records, are
        taken at the vertex passes; the training records are not (:meth:`after_advance` reads them)."""
        return self.suffix_base is not None or bool(self.watchers)

    @property
    def indirect(self) -> bool:
        """``cache_target=indirect``: a terminating vertex estimates its direct light, which goes to the record's
        direct-light rows; a continued vertex's own estimate stays in the pixel (``renderer.debias``)."""
        return self.direct_base is not None

    # ------------------------------------------------------------------ rows
    def rows(self, ly: Any, I: Tensor, j: Tensor | int) -> Tensor:
        dest = I[ly.i("dest")]
        j = torch.as_tensor(j, device=dest.device)
        if j.dim() < 2:  # per slot or one for all; (R, 1): every row of every slot, (R, K)
            j = j.expand_as(dest)
        rec_base = I[ly.i("rec_base")]
        rec = self.n_pixels + rec_base + j - 1
        if self.direct_base is not None:  # rows V+1..2V of a slot: its records' direct light
            rec = torch.where(j > self.V, self.direct_base + rec_base + j - self.V - 1, rec)
        rows = torch.where((j > 0) & (rec_base >= 0), rec, dest)
        if self.suffix_base is not None:  # a continued render path's row 1: its sample's suffix row
            suffix = (j == 1) & (rec_base < 0) & (I[ly.i("never")] == CONTINUED)
            rows = torch.where(suffix, self.suffix_base + I[ly.i("pid")], rows)
        return rows

    def current_rows(self, ly: Any, I: Tensor) -> Tensor:
        never = I[ly.i("never")] if self.suffix_base is not None else None
        return self.rows(ly, I, accumulator_row(I[ly.i("rec_base")], I[ly.i("n")], self.V, never))

    def direct_rows(self, ly: Any, I: Tensor) -> Tensor:
        """With ``cache_target=indirect`` the direct light of a recorded vertex (``rec >= 0``: set at the vertex,
        kept until the next one) goes to that record's direct-light row."""
        rows = self.current_rows(ly, I)
        if self.direct_base is None:
            return rows
        rec = I[ly.i("rec")]
        return torch.where(rec >= 0, self.direct_base + rec, rows)

    def shadow_rows(self, ly: Any, I: Tensor, here: Any, qd: Tensor) -> Tensor:
        rows = self.direct_rows(ly, I)
        if here is not None and self.indirect:  # the continued vertex's own estimate: the pixel's
            rows = torch.where(here[qd], I[ly.i("dest")], rows)
        return rows

    def starts_segment(self, ly: Any, I: Tensor) -> Tensor:
        """A training path's camera ray takes no part (its light would be discarded)."""
        return ~((I[ly.i("rec_base")] >= 0) & (I[ly.i("n")] == 0))

    # ------------------------------------------------------------------ harvest and vertex passes
    def harvest(self, ly: Any, F: Tensor, I: Tensor, flight: Tensor) -> None:
        q = (flight == QUERY).nonzero().squeeze(1)
        if len(q):
            Iq = I[:, q]
            self.queries["x"].append(F[ly.f("o")][:, q].T)
            self.queries["d"].append(F[ly.f("d")][:, q].T)
            self.queries["w"].append(F[ly.f("beta")][:, q].T)
            self.queries["dest"].append(self.current_rows(ly, Iq))
            self.queries["pid"].append(Iq[ly.i("pid")])
            if self.suffix_base is not None:
                self.queries["cont"].append(torch.zeros(len(q), dtype=torch.bool, device=q.device))
        is_train = I[ly.i("rec_base")] >= 0
        train = is_train & ((I[ly.i("n")] > 0) | (flight == QUERY))
        if bool(train.any()):
            self.scattered[I[ly.i("pid")][train] - self.n_render] = True
        if self.finished is not None:
            self.finished[I[ly.i("pid")][is_train] - self.n_render] = True

    def after_advance(self, ly: Any, F: Tensor, I: Tensor) -> None:
        """The training records of the tail's fused vertices: a slot's last record (``rec``), its position ``o``
        and direction ``d_in`` stay until its next collision, so a record written at an earlier call (or pass) is
        written again with the same values. Not where the slot waits at its next collision (``VERTEX``: the vertex
        waits for the last one's shadow ray), whose position ``o`` already holds: the record was written when its
        own vertex ran, at the call that left the slot in flight."""
        rec = I[ly.i("rec")]
        r = ((rec >= 0) & (I[ly.i("occupied")] != 0) & (I[ly.i("flight")] != VERTEX)).nonzero().squeeze(1)
        if len(r):
            self._record(rec[r], F[ly.f("o")][:, r].T, F[ly.f("d_in")][:, r].T)

    def after_advance_ahead(self, ly: Any, I: Tensor) -> bool:
        """A live training path with fewer than V vertices can still write a record (its records are written at its
        first V vertices: ``decide``); a record already current was written by the last :meth:`after_advance`."""
        n = I[ly.i("n")]
        return bool(((I[ly.i("occupied")] != 0) & (I[ly.i("rec_base")] >= 0) & (n < self.V)).any())

    def vertex_pass(self, ly: Any, F_in: Tensor, I_in: Tensor, F_out: Tensor, I_out: Tensor) -> Tensor | None:
        """Returns the slots continued past their cache termination at this vertex (``renderer.debias``)."""
        here = None
        if self.suffix_base is not None:
            here = just_continued(I_in[ly.i("never")], I_out[ly.i("never")])
        if self.watchers:
            event = self.event(ly, F_in, I_in, F_out, I_out, here)
            for w in self.watchers:
                w.record(event)
        if here is not None:
            c = here.nonzero().squeeze(1)
            if len(c):  # the cache's control-variate query at the vertex: weight beta (1 - 1/q)
                Ic, beta = I_in[:, c], F_in[ly.f("beta")][:, c].T
                self.queries["x"].append(F_out[ly.f("o")][:, c].T)
                self.queries["d"].append(F_in[ly.f("d")][:, c].T)
                self.queries["w"].append(beta * (1.0 - 1.0 / self.debias_q))
                self.queries["dest"].append(Ic[ly.i("dest")])
                self.queries["pid"].append(Ic[ly.i("pid")])
                self.queries["cont"].append(torch.ones(len(c), dtype=torch.bool, device=c.device))
                self.continued["pid"].append(Ic[ly.i("pid")])
                self.continued["beta"].append(beta)
        rec = I_out[ly.i("rec")]
        r = (rec >= 0).nonzero().squeeze(1)
        if len(r):  # the incoming direction (before scattering)
            self._record(rec[r], F_out[ly.f("o")][:, r].T, F_in[ly.f("d")][:, r].T)
        return here

    def _record(self, slots: Tensor, x: Tensor, d: Tensor) -> None:
        """Write training records ``slots`` of the pool: position ``x`` and incoming direction ``d`` ``(n, 3)``."""
        self.rec_x[slots] = x
        self.rec_d[slots] = d
        self.rec_valid[slots] = True

    def event(self, ly: Any, F_in: Tensor, I_in: Tensor, F_out: Tensor, I_out: Tensor,
              here: Tensor | None = None) -> VertexEvent:
        """Render paths only (``sample`` -1 for training paths); a terminating vertex estimates its direct light
        only with ``cache_target=indirect``; a continued one is not MIS-weighted (indirect) or carries ``1/q``
        (full)."""
        render = I_in[ly.i("rec_base")] < 0
        go = I_out[ly.i("flight")] != QUERY
        nee = go | self.indirect
        mis, scale = go, torch.ones(len(go), device=F_in.device)
        if here is not None:
            if self.indirect:
                mis = mis & ~here
            else:
                scale = torch.where(here, scale / self.debias_q, scale)
        return VertexEvent(n=I_in[ly.i("n")], sample=torch.where(render, I_in[ly.i("pid")], -1),
                           x=F_out[ly.f("o")].T, d=F_in[ly.f("d")].T, beta=F_in[ly.f("beta")].T, nee=nee, mis=mis,
                           scale=scale)
