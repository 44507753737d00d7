"""The wavefront loop around the step: refill, harvest, compaction, the vertex pass and the shadow queue.

A fixed working set of slots advances by :meth:`Machine.track` calls. Every ``REFILL_EVERY``-th call the
finished slots are *harvested* -- their radiance rows land in the accumulator, escaped paths add the
environment (MIS-weighted against next-event estimation unless a camera ray), terminated paths hand their
cache query to the caller -- and refilled with new paths from the queue; once the queue is empty the state is
compacted whenever fewer than 90 % of the slots are live. Every ``SCATTER_EVERY``-th call the slots waiting at a
vertex run :meth:`Machine.vertex` (a subset: gathered, stepped, scattered back); next-event requests of an
estimator without a per-step form are queued and traced in batches of ``shadow_batch`` rays. With
``point_light_sampling=equiangular`` the segments the slots start (camera rays, scattering rays) are queued
for the point lights' equi-angular estimate (:class:`EquiangularQueue`). With ``renderer.reuse`` the render
paths' reuse vertices are recorded for the reuse pass (:mod:`nrc.render.wavefront.reuse`).

Accumulator rows: row 0 of a slot is ``dest`` (a pixel, or a training path's discard row); rows ``j >= 1``
(``nrc``) are training records, ``n_pixels + rec_base + j - 1``. With ``cache_target=indirect`` the direct
light of a recorded vertex (its next-event estimate, the MIS-weighted environment its sampled direction
reaches) goes to a second block of record rows (:attr:`Harvest.direct_base`), so that the caller can take it
out of the record's target.

With ``renderer.debias`` (:mod:`nrc.render.radiance_caching.debias`) a render path continued past its cache
termination gives its suffix (everything it gathers from that vertex on, with throughput ``beta / q``) to a row of
its own, :attr:`Harvest.suffix_base` + its sample id, and its cache query (weight ``beta (1 - 1/q)``) is recorded
at the vertex pass; the caller adds the suffix rows to the pixels. Under ``cache_target=indirect`` the vertex's
own next-event estimate (light sampling alone, throughput ``beta``) stays in the pixel's row.

Memory: the state (``Layout``), the shadow queue (at most ``shadow_batch`` + one vertex pass of requests)
and the caller's accumulator; independent of image size and spp.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.machine import MIN_SLOTS, Machine, SceneInputs
from nrc.render.wavefront.state import (CONTINUED, DONE, ESCAPED, FLIGHT, QUERY, VERTEX, Layout, accumulator_row,
                                       just_continued)
from nrc.transport.light_sampling import LightSampler, power_heuristic
from nrc.transport.rng import hash32
from nrc.transport.rng import uniforms as counter_uniforms

REFILL_EVERY = 4  # calls between refills while the camera queue lasts (finished slots idle ~1.5 steps)
# calls between vertex passes: slots at a vertex wait ~0.5 step longer (+3.6 % slot-steps) for half the
# passes' fixed cost (nonzero, gathers; eager): ~+15 % samples/s at 2 threads (docs/benchmarks.md)
SCATTER_EVERY = 2
# once the queue is empty, compact when fewer than this fraction of the slots are live (every step's cost grows
# with the slot count; NRC frame at 160x90, trace: 0.5 -> 0.26 s compiled / 0.76 s eager, 0.9 -> 0.25 / 0.67 s)
COMPACT_BELOW = 0.9


class BatchQueue:
    """Work items ``(columns..., dest)`` collected as the slots produce them and traced ``batch`` rows at a time
    (:meth:`trace` returns the RGB contributions ``(N, 3)``, added to the accumulator rows ``dest``)."""

    def __init__(self, batch: int) -> None:
        self.batch = batch
        self.items: list[tuple[Tensor, ...]] = []
        self.queued, self.done, self.seconds = 0, 0, 0.0

    def push(self, *columns: Tensor, acc: Tensor) -> None:
        self.items.append(columns)
        self.queued += len(columns[0])
        if self.queued >= self.batch:
            self.flush(acc)

    def flush(self, acc: Tensor) -> None:
        if not self.items:
            return
        t0 = time.perf_counter()
        *cols, dest = (torch.cat(c) for c in zip(*self.items))
        self.items.clear()
        self.queued = 0
        acc.index_add_(0, dest, self.trace(*cols))
        self.done += len(dest)
        self.seconds += time.perf_counter() - t0

    def trace(self, *columns: Tensor) -> Tensor:
        raise NotImplementedError


class ShadowQueue(BatchQueue):
    """Next-event requests ``(x, wi, t1, weight, dest)`` for a transmittance estimator without a per-step form
    (``transmittance`` other than ratio tracking): ``weight x T(x -> x + t1 wi)``."""

    def __init__(self, estimator: Any, grid: Any, majorants: Any, batch: int, gen: torch.Generator) -> None:
        super().__init__(batch)
        self.estimator, self.grid, self.majorants, self.gen = estimator, grid, majorants, gen

    def trace(self, x: Tensor, wi: Tensor, t1: Tensor, weight: Tensor) -> Tensor:
        T = self.estimator(self.grid, self.majorants, x, wi, torch.zeros_like(t1), t1, self.gen)
        return weight * T[:, None]


class EquiangularQueue(BatchQueue):
    """Flight segments ``(o, d, ta, tb, beta, key, cnt, dest)`` whose point-light direct light is estimated by
    equi-angular sampling (``renderer.point_light_sampling=equiangular``, :mod:`nrc.transport.equiangular`):
    queued as the segments start (camera rays as they are spawned, scattering rays after their vertex, up to the
    one that leads to vertex ``max_scatter``), contributions added to the segment's accumulator row.

    The distance and the light choice come from the path's counter-based draw ``(hash(key ^ SALT), cnt)`` (its
    own stream: the step's draws use ``(key, cnt)``), so they depend on the path, not on the batching; the
    transmittance estimator draws from ``gen`` like the shadow queue's."""

    SALT = 0x5EA5EED

    def __init__(self, sampler: Any, max_scatter: int, batch: int, gen: torch.Generator) -> None:
        super().__init__(batch)
        self.sampler, self.max_scatter, self.gen = sampler, max_scatter, gen

    def trace(self, o: Tensor, d: Tensor, ta: Tensor, tb: Tensor, beta: Tensor, key: Tensor, cnt: Tensor) -> Tensor:
        u = torch.stack(counter_uniforms(hash32(key ^ self.SALT), cnt, 2), 1)
        return self.sampler.contribution(o, d, ta, tb, beta, u, self.gen)


@dataclass
class Harvest:
    """What ``nrc`` collects besides the accumulator (``pt`` needs none of it)."""

    n_pixels: int
    n_render: int
    rec_x: Tensor  # (N_train * V, 3) training-record positions, written at recorded vertices
    rec_d: Tensor
    rec_valid: Tensor
    scattered: Tensor  # (N_train,) bool
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
    debias_indirect: bool = False  # cache_target=indirect: the continued vertex's own estimate stays in the pixel


class Wavefront:
    """Runs ``total`` paths through ``machine`` into ``acc``.

    Args:
        machine: the step functions; inputs: the scene tensors.
        lights: the eager light sampler (environment radiance and pdf at harvest).
        slots: working-set size; shadow: the queue for external estimators (``None``: inline ratio tracking).
        harvest: the NRC collections (``None`` for ``pt``).
    """

    def __init__(self, machine: Machine, inputs: SceneInputs, lights: LightSampler, slots: int,
                 shadow: ShadowQueue | None, harvest: Harvest | None = None,
                 equiangular: EquiangularQueue | None = None, reuse: Any = None) -> None:
        self.machine, self.inputs, self.lights, self.slots = machine, inputs, lights, slots
        self.reuse = reuse  # a reuse.VertexRecord: the render paths' reuse vertices are recorded into it
        self.layout: Layout = machine.step.layout
        self.shadow, self.harvest, self.equiangular = shadow, harvest, equiangular
        self.counts = {"tracking_steps": 0, "shadow_steps": 0, "shadow_rays": 0, "scatter_events": 0,
                       "iterations": 0, "slot_steps": 0}
        self.timers = {"step": 0.0, "scatter": 0.0, "refill": 0.0}

    def _rows(self, I: Tensor, j: Tensor | int) -> Tensor:
        """Accumulator index of row ``j`` (per slot or one for all) of the given slots."""
        ly = self.layout
        dest = I[ly.i("dest")]
        if not ly.nrc:
            return dest
        hv = self.harvest
        j = torch.as_tensor(j, device=dest.device).expand_as(dest)
        rec_base = I[ly.i("rec_base")]
        rec = hv.n_pixels + rec_base + j - 1
        rows = torch.where((j > 0) & (rec_base >= 0), rec, dest)
        if hv.suffix_base is not None:  # a continued render path's row 1: its sample's suffix row
            suffix = (j == 1) & (rec_base < 0) & (I[ly.i("never")] == CONTINUED)
            rows = torch.where(suffix, hv.suffix_base + I[ly.i("pid")], rows)
        return rows

    def _direct_rows(self, I: Tensor) -> Tensor:
        """Accumulator rows of the given slots' current contributions, except that with ``cache_target=indirect``
        the direct light of a recorded vertex (``rec >= 0``: set at the vertex, kept until the next one) goes to
        that record's direct-light row."""
        rows = self._rows(I, self._current_row(I))
        hv = self.harvest
        if hv is None or hv.direct_base is None:
            return rows
        rec = I[self.layout.i("rec")]
        return torch.where(rec >= 0, hv.direct_base + rec, rows)

    def _current_row(self, I: Tensor) -> Tensor | int:
        ly = self.layout
        if not ly.nrc:
            return 0
        never = I[ly.i("never")] if self.harvest.suffix_base is not None else None
        return accumulator_row(I[ly.i("rec_base")], I[ly.i("n")], ly.rows - 1, never)

    def _push_segments(self, F: Tensor, I: Tensor, acc: Tensor) -> None:
        """Queue the equi-angular estimate of the segments the given slots start (flying, vertex count below
        ``max_scatter``; a training path's camera ray, whose light would be discarded, excepted)."""
        ly, eq = self.layout, self.equiangular
        n = I[ly.i("n")]
        go = (I[ly.i("flight")] == FLIGHT) & (n < eq.max_scatter) & (F[ly.f("tmax")] > F[ly.f("t")])
        if ly.nrc:
            go = go & ~((I[ly.i("rec_base")] >= 0) & (n == 0))
        idx = go.nonzero().squeeze(1)
        if not len(idx):
            return
        Fi, Ii = F[:, idx], I[:, idx]
        eq.push(Fi[ly.f("o")].T.contiguous(), Fi[ly.f("d")].T.contiguous(), Fi[ly.f("t")], Fi[ly.f("tmax")],
                Fi[ly.f("beta")].T, Ii[ly.i("key")], Ii[ly.i("cnt")], self._rows(Ii, self._current_row(Ii)), acc=acc)

    def _harvest(self, F: Tensor, I: Tensor, done: Tensor, acc: Tensor) -> None:
        ly = self.layout
        Fd, Id = F[:, done], I[:, done]
        L = Fd[ly.f("L")]
        for j in range(ly.rows):
            acc.index_add_(0, self._rows(Id, j), L[3 * j:3 * j + 3].T)
        flight = Id[ly.i("flight")]
        if self.lights.has_env:
            e = (flight == ESCAPED).nonzero().squeeze(1)
            if len(e):
                d = Fd[ly.f("d")][:, e].T.contiguous()
                pdf = Fd[ly.f("pdf")][e]
                # pdf 0: a camera ray (no MIS); pdf < 0: a continued path's first segment under cache_target=indirect,
                # whose vertex's direct light came from light sampling alone (renderer.debias)
                w = torch.where(pdf > 0, power_heuristic(pdf, self.lights.env_pdf(d)),
                                (pdf == 0).to(pdf.dtype))
                Ie = Id[:, e]
                # escaped from a recorded vertex: the MIS-weighted environment is that record's direct light
                acc.index_add_(0, self._direct_rows(Ie), Fd[ly.f("beta")][:, e].T * self.lights.env_radiance(d) * w[:, None])
        c = self.counts
        c["tracking_steps"] += int(Id[ly.i("cnt")].sum())
        c["shadow_steps"] += int(Id[ly.i("n_shadow_steps")].sum())
        hv = self.harvest
        if hv is None:
            return
        q = (flight == QUERY).nonzero().squeeze(1)
        if len(q):
            Iq = Id[:, q]
            hv.queries["x"].append(Fd[ly.f("o")][:, q].T)
            hv.queries["d"].append(Fd[ly.f("d")][:, q].T)
            hv.queries["w"].append(Fd[ly.f("beta")][:, q].T)
            hv.queries["dest"].append(self._rows(Iq, self._current_row(Iq)))
            hv.queries["pid"].append(Iq[ly.i("pid")])
            if hv.suffix_base is not None:
                hv.queries["cont"].append(torch.zeros(len(q), dtype=torch.bool, device=q.device))
        train = (Id[ly.i("rec_base")] >= 0) & ((Id[ly.i("n")] > 0) | (flight == QUERY))
        if bool(train.any()):
            hv.scattered[Id[ly.i("pid")][train] - hv.n_render] = True

    def _vertex_pass(self, F: Tensor, I: Tensor, acc: Tensor) -> None:
        ly = self.layout
        sc = (I[ly.i("flight")] == VERTEX).nonzero().squeeze(1)
        if not len(sc):
            return
        self.counts["scatter_events"] += len(sc)
        Fi, Ii = F.index_select(1, sc), I.index_select(1, sc)
        Fs, Is = self.machine.vertex(Fi, Ii, self.inputs)
        if self.reuse is not None:
            self.reuse.record(ly, Fi, Ii, Fs, Is)
        hv = self.harvest
        here = None  # renderer.debias: the slots continued past their cache termination at this vertex
        if hv is not None and hv.suffix_base is not None:
            here = just_continued(Ii[ly.i("never")], Is[ly.i("never")])
            c = here.nonzero().squeeze(1)
            if len(c):  # the cache's control-variate query at the vertex: weight beta (1 - 1/q)
                Ic, beta = Ii[:, c], Fi[ly.f("beta")][:, c].T
                hv.queries["x"].append(Fs[ly.f("o")][:, c].T)
                hv.queries["d"].append(Fi[ly.f("d")][:, c].T)
                hv.queries["w"].append(beta * (1.0 - 1.0 / hv.debias_q))
                hv.queries["dest"].append(Ic[ly.i("dest")])
                hv.queries["pid"].append(Ic[ly.i("pid")])
                hv.queries["cont"].append(torch.ones(len(c), dtype=torch.bool, device=c.device))
                hv.continued["pid"].append(Ic[ly.i("pid")])
                hv.continued["beta"].append(beta)
        if hv is not None:
            rec = Is[ly.i("rec")]
            r = (rec >= 0).nonzero().squeeze(1)
            if len(r):
                slot = rec[r]
                hv.rec_x[slot] = Fs[ly.f("o")][:, r].T
                hv.rec_d[slot] = F[ly.f("d")][:, sc[r]].T  # the incoming direction (before scattering)
                hv.rec_valid[slot] = True
        if self.shadow is None:
            self.counts["shadow_rays"] += int((Is[ly.i("shadow")] != 0).sum())
        else:
            qd = (Is[ly.i("shadow")] == 2).nonzero().squeeze(1)
            if len(qd):
                Iq = Is[:, qd]
                rows = self._direct_rows(Iq)
                if here is not None and hv.debias_indirect:  # the continued vertex's own estimate: the pixel's
                    rows = torch.where(here[qd], Iq[ly.i("dest")], rows)
                self.shadow.push(Fs[ly.f("o")][:, qd].T.contiguous(), Fs[ly.f("wi")][:, qd].T.contiguous(),
                                 Fs[ly.f("tse")][qd], Fs[ly.f("csh")][:, qd].T, rows, acc=acc)
                Is[ly.i("shadow"), qd] = 0
        if self.equiangular is not None:
            self._push_segments(Fs, Is, acc)
        F.index_copy_(1, sc, Fs)
        I.index_copy_(1, sc, Is)

    def run(self, total: int, new_paths: Callable[[Tensor], tuple[Tensor, Tensor]], acc: Tensor,
            on_done: Callable[[int], None] | None = None) -> None:
        """Trace paths ``0 .. total-1`` (``new_paths(ids) -> (F, I)`` packs fresh ones) into ``acc``."""
        ly, dev, c, tm = self.layout, acc.device, self.counts, self.timers
        S = max(min(self.slots, total), 2)
        F, I = ly.zeros(S, dev)
        next_id, calls = 0, 0
        i_flight, i_shadow, i_occ = ly.i("flight"), ly.i("shadow"), ly.i("occupied")
        while True:
            if calls % REFILL_EVERY == 0:
                t_rf = time.perf_counter()
                fl = I[i_flight]
                free = ((fl == DONE) | (fl >= QUERY)) & (I[i_shadow] == 0)
                S = I.shape[1]
                # Once the queue is empty, harvest only to compact or to finish: the tail's calls are short, and
                # a harvest (a few dozen small ops) costs more than a step there.
                due = True
                if next_id >= total:
                    n_free = int(free.sum())
                    due = n_free == S or (S - n_free < COMPACT_BELOW * S and S > MIN_SLOTS)
                if due:
                    idx = free.nonzero().squeeze(1)
                    k = 0
                    if len(idx):
                        done = idx[I[i_occ, idx] != 0]
                        if len(done):
                            self._harvest(F, I, done, acc)
                            if on_done is not None:
                                on_done(len(done))
                        I[i_occ, idx] = 0
                        I[i_flight, idx] = DONE
                        k = min(len(idx), total - next_id)
                        if k:
                            slots = idx[:k]
                            Fn, In = new_paths(torch.arange(next_id, next_id + k, device=dev))
                            F.index_copy_(1, slots, Fn)
                            I.index_copy_(1, slots, In)
                            if self.equiangular is not None:
                                self._push_segments(Fn, In, acc)
                            next_id += k
                    live = S - len(idx) + k
                    if live == 0:
                        tm["refill"] += time.perf_counter() - t_rf
                        break
                    if next_id >= total and live < COMPACT_BELOW * S and S > MIN_SLOTS:
                        fl = I[i_flight]
                        free = ((fl == DONE) | (fl >= QUERY)) & (I[i_shadow] == 0)
                        keep = (~free).nonzero().squeeze(1)
                        if len(keep) < MIN_SLOTS:  # pad with idle slots
                            keep = torch.cat([keep, free.nonzero().squeeze(1)[: MIN_SLOTS - len(keep)]])
                        F, I = F[:, keep].contiguous(), I[:, keep].contiguous()
                tm["refill"] += time.perf_counter() - t_rf
            t_st = time.perf_counter()
            F, I = self.machine.track(F, I, self.inputs)
            c["iterations"] += 1
            calls += 1
            c["slot_steps"] += I.shape[1] * self.machine.steps_per_call
            t_sc = time.perf_counter()
            tm["step"] += t_sc - t_st
            if calls % SCATTER_EVERY:
                continue
            self._vertex_pass(F, I, acc)
            tm["scatter"] += time.perf_counter() - t_sc
        if self.shadow is not None:
            self.shadow.flush(acc)
            c["shadow_rays"] += self.shadow.done
            tm["shadow"] = self.shadow.seconds
        if self.equiangular is not None:
            self.equiangular.flush(acc)
            c["equiangular_segments"] = self.equiangular.done
            tm["equiangular"] = self.equiangular.seconds
