"""The wavefront loop around the step: refill, harvest, compaction, the vertex pass and the shadow queue.

A fixed working set of slots advances by :meth:`Machine.track` calls. Every ``REFILL_EVERY``-th call the
finished slots are *harvested* -- their radiance rows land in the accumulator, escaped paths add the
environment (MIS-weighted against next-event estimation unless a camera ray), paths that ended at a vertex
(``QUERY``) go to the renderer's collector -- and refilled with new paths from the queue; once the queue is empty the state is
compacted whenever fewer than 90 % of the slots are live. Every ``SCATTER_EVERY``-th call the slots waiting at a
vertex run :meth:`Machine.vertex` (a subset: gathered, stepped, scattered back); next-event requests of an
estimator without a per-step form are queued and traced in batches of ``shadow_batch`` rays. With
``point_light_sampling=equiangular`` the segments the slots start (camera rays, scattering rays) are queued
for the point lights' equi-angular estimate (:class:`EquiangularQueue`).

What a renderer adds is its collector's (:class:`nrc.render.wavefront.program.Collector`): the accumulator rows of
a slot's contributions (``pt``: row ``dest``, the pixel), what it keeps of harvested slots (``nrc``: cache
queries) and of each vertex pass (``nrc``: training records; its watchers, e.g. the reservoir reuse pass's
vertex record, get a :class:`~nrc.render.wavefront.program.VertexEvent`).

Memory: the state (``Layout``), the shadow queue (at most ``shadow_batch`` + one vertex pass of requests)
and the caller's accumulator; independent of image size and spp.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.machine import MIN_SLOTS, Machine, SceneInputs
from nrc.render.wavefront.program import Collector
from nrc.render.wavefront.state import DONE, ESCAPED, FLIGHT, QUERY, VERTEX, Layout
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
class Queues:
    """The batch queues of a wavefront (``None``: not used)."""

    shadow: ShadowQueue | None = None
    """Next-event requests for a transmittance estimator without a per-step form (``None``: inline ratio
    tracking in the step)."""
    equiangular: EquiangularQueue | None = None
    """Flight segments for the point lights' equi-angular estimate."""


class Wavefront:
    """Runs ``total`` paths through ``machine`` into ``acc``.

    Args:
        machine: the step functions; inputs: the scene tensors.
        lights: the eager light sampler (environment radiance and pdf at harvest).
        slots: working-set size.
        queues: the shadow and equi-angular queues (default: none).
        collector: the renderer's collector (:mod:`nrc.render.wavefront.program`; default: ``pt``'s).
    """

    def __init__(self, machine: Machine, inputs: SceneInputs, lights: LightSampler, slots: int,
                 queues: Queues | None = None, collector: Collector | None = None) -> None:
        self.machine, self.inputs, self.lights, self.slots = machine, inputs, lights, slots
        self.layout: Layout = machine.step.layout
        queues = queues if queues is not None else Queues()
        self.shadow, self.equiangular = queues.shadow, queues.equiangular
        self.collector = collector if collector is not None else Collector()
        self.counts = {"tracking_steps": 0, "shadow_steps": 0, "shadow_rays": 0, "scatter_events": 0,
                       "iterations": 0, "slot_steps": 0}
        self.timers = {"step": 0.0, "scatter": 0.0, "refill": 0.0}

    def _push_segments(self, F: Tensor, I: Tensor, acc: Tensor) -> None:
        """Queue the equi-angular estimate of the segments the given slots start (flying, vertex count below
        ``max_scatter``, taken by the collector)."""
        ly, eq, col = self.layout, self.equiangular, self.collector
        n = I[ly.i("n")]
        go = (I[ly.i("flight")] == FLIGHT) & (n < eq.max_scatter) & (F[ly.f("tmax")] > F[ly.f("t")])
        take = col.starts_segment(ly, I)
        if take is not None:
            go = go & take
        idx = go.nonzero().squeeze(1)
        if not len(idx):
            return
        Fi, Ii = F[:, idx], I[:, idx]
        eq.push(Fi[ly.f("o")].T.contiguous(), Fi[ly.f("d")].T.contiguous(), Fi[ly.f("t")], Fi[ly.f("tmax")],
                Fi[ly.f("beta")].T, Ii[ly.i("key")], Ii[ly.i("cnt")], col.current_rows(ly, Ii), acc=acc)

    def _harvest(self, F: Tensor, I: Tensor, done: Tensor, acc: Tensor) -> None:
        ly, col = self.layout, self.collector
        Fd, Id = F[:, done], I[:, done]
        L = Fd[ly.f("L")]
        for j in range(ly.rows):
            acc.index_add_(0, col.rows(ly, Id, j), L[3 * j:3 * j + 3].T)
        flight = Id[ly.i("flight")]
        if self.lights.has_env:
            e = (flight == ESCAPED).nonzero().squeeze(1)
            if len(e):
                d = Fd[ly.f("d")][:, e].T.contiguous()
                pdf = Fd[ly.f("pdf")][e]
                # pdf 0: a camera ray (no MIS)
                w = torch.where(pdf > 0, power_heuristic(pdf, self.lights.env_pdf(d)), torch.ones_like(pdf))
                Ie = Id[:, e]
                if ly.skip_env:  # segments whose escape does not count the environment (Decision.skip_env)
                    w = torch.where(Ie[ly.i("skip_env")] != 0, torch.zeros_like(w), w)
                # the MIS-weighted environment is the direct light of the vertex the segment left
                acc.index_add_(0, col.direct_rows(ly, Ie), Fd[ly.f("beta")][:, e].T * self.lights.env_radiance(d) * w[:, None])
        c = self.counts
        c["tracking_steps"] += int(Id[ly.i("cnt")].sum())
        c["shadow_steps"] += int(Id[ly.i("n_shadow_steps")].sum())
        col.harvest(ly, Fd, Id, flight)

    def _vertex_pass(self, F: Tensor, I: Tensor, acc: Tensor) -> None:
        ly, col = self.layout, self.collector
        sc = (I[ly.i("flight")] == VERTEX).nonzero().squeeze(1)
        if not len(sc):
            return
        self.counts["scatter_events"] += len(sc)
        Fi, Ii = F.index_select(1, sc), I.index_select(1, sc)
        Fs, Is = self.machine.vertex(Fi, Ii, self.inputs)
        info = col.vertex_pass(ly, Fi, Ii, Fs, Is)
        if self.shadow is None:
            self.counts["shadow_rays"] += int((Is[ly.i("shadow")] != 0).sum())
        else:
            qd = (Is[ly.i("shadow")] == 2).nonzero().squeeze(1)
            if len(qd):
                Iq = Is[:, qd]
                self.shadow.push(Fs[ly.f("o")][:, qd].T.contiguous(), Fs[ly.f("wi")][:, qd].T.contiguous(),
                                 Fs[ly.f("tse")][qd], Fs[ly.f("csh")][:, qd].T, col.shadow_rows(ly, Iq, info, qd),
                                 acc=acc)
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
