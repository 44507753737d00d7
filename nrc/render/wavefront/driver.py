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
# passes' fixed cost (nonzero, gathers; eager): ~+15 % samples/s at 2 threads (docs/measurements/speed.md)
SCATTER_EVERY = 2
# once the queue is empty, compact when fewer than this fraction of the slots are live (every step's cost grows
# with the slot count; NRC frame at 160x90, trace: 0.5 -> 0.26 s compiled / 0.76 s eager, 0.9 -> 0.25 / 0.67 s)
COMPACT_BELOW = 0.9
# once the queue is empty and at most this many slots are live, the tail runs fused calls (Machine.advance: a
# tracking step and the vertices it reaches, one thread), TAIL_CALLS between harvests (docs/measurements/nrc_frames.md)
TAIL_SLOTS = 256
TAIL_CALLS = 16
# the tail harvests (and compacts) once more than this fraction of its slots is free, or all are
TAIL_FREE = 0.25


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
        Fd, Id = F.index_select(1, done), I.index_select(1, done)  # (index_select: a third of F[:, done]'s time)
        L = Fd[ly.f("L")]  # (3 R, K)
        if ly.rows == 1:
            acc.index_add_(0, col.rows(ly, Id, 0), L.T)
        else:  # every row of every slot in one add
            rows = col.rows(ly, Id, torch.arange(ly.rows, device=L.device)[:, None])  # (R, K)
            acc.index_add_(0, rows.reshape(-1), L.reshape(ly.rows, 3, -1).transpose(1, 2).reshape(-1, 3))
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
        self._count(Id, 1)
        col.harvest(ly, Fd, Id, flight)

    def _count(self, I: Tensor, sign: int) -> None:
        """Add (``sign`` 1) or take back (-1) the work counters that slots ``I`` hold: tracking and shadow-ray
        steps, scattering events (vertices that went on, and a path's last one that ended it as a query) and the
        shadow rays traced in the slot. Read at harvest, and for carried slots at the end and start of a run, so a
        run counts the work done in it."""
        ly = self.layout
        sums = torch.stack([I[ly.i("cnt")].sum(), I[ly.i("n_shadow_steps")].sum(), I[ly.i("n")].sum()
                            + (I[ly.i("flight")] == QUERY).sum(), I[ly.i("n_shadow")].sum()]).tolist()
        for name, v in zip(("tracking_steps", "shadow_steps", "scatter_events", "shadow_rays"), sums):
            self.counts[name] += sign * int(v)

    def _vertex_pass(self, F: Tensor, I: Tensor, acc: Tensor) -> None:
        ly, col = self.layout, self.collector
        # a vertex waits for the shadow ray of the one before it (which the free flight overtook)
        sc = ((I[ly.i("flight")] == VERTEX) & (I[ly.i("shadow")] == 0)).nonzero().squeeze(1)
        if not len(sc):
            return
        Fi, Ii = F.index_select(1, sc), I.index_select(1, sc)
        Fs, Is = self.machine.vertex(Fi, Ii, self.inputs)
        info = col.vertex_pass(ly, Fi, Ii, Fs, Is)
        if self.shadow is not None:
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

    @property
    def fusable(self) -> bool:
        """The tail runs fused calls (:meth:`Machine.advance`): the step traces its shadow rays, no queue waits for
        a vertex pass and the collector needs none (:attr:`Collector.needs_vertex_passes`; what it keeps of the
        fused vertices it reads from the state after each call, :meth:`Collector.after_advance`)."""
        return (self.machine.fusable and self.shadow is None and self.equiangular is None
                and not self.collector.needs_vertex_passes)

    def _free(self, I: Tensor) -> Tensor:
        """``(S,)`` bool: slots without a path in flight (done, escaped, a query) and no pending shadow ray."""
        fl = I[self.layout.i("flight")]
        return ((fl == DONE) | (fl >= QUERY)) & (I[self.layout.i("shadow")] == 0)

    def _retire(self, F: Tensor, I: Tensor, idx: Tensor, acc: Tensor, on_done: Callable[[int], None] | None) -> None:
        """Harvest the occupied slots among the free slots ``idx`` and mark them all idle."""
        ly = self.layout
        done = idx[I[ly.i("occupied"), idx] != 0]
        if len(done):
            self._harvest(F, I, done, acc)
            if on_done is not None:
                on_done(len(done))
        I[ly.i("occupied"), idx] = 0
        I[ly.i("flight"), idx] = DONE

    def run(self, total: int, new_paths: Callable[[Tensor], tuple[Tensor, Tensor]], acc: Tensor,
            on_done: Callable[[int], None] | None = None, carry: tuple[Tensor, Tensor] | None = None,
            keep: Callable[[Tensor], Tensor] | None = None,
            on_tail: Callable[[], None] | None = None) -> tuple[Tensor, Tensor] | None:
        """Trace paths ``0 .. total-1`` (``new_paths(ids) -> (F, I)`` packs fresh ones) into ``acc``.

        ``carry``: slots of an earlier run that go on here (their rows of ``acc`` must still be valid). ``keep``:
        ``keep(I) -> (S,)`` bool marks the slots that may be left in flight: once every path has started and every
        live slot is marked, the run stops and returns those slots (``(F, I)``, to be carried into a later run);
        without ``keep`` (or when nothing is left) it returns ``None``. ``on_tail()`` is called once, as the run's
        last slots go on in one-thread fused calls (the tail): from then on the other cores are free (the NRC
        renderer trains there). The queues are traced before it returns.
        """
        out = self._run(total, new_paths, acc, on_done, carry, keep, on_tail)
        self._finish(acc)
        return out

    def _run(self, total: int, new_paths: Callable[[Tensor], tuple[Tensor, Tensor]], acc: Tensor,
             on_done: Callable[[int], None] | None, carry: tuple[Tensor, Tensor] | None,
             keep: Callable[[Tensor], Tensor] | None,
             on_tail: Callable[[], None] | None) -> tuple[Tensor, Tensor] | None:
        ly, dev, c, tm = self.layout, acc.device, self.counts, self.timers
        n_carry = 0 if carry is None else carry[0].shape[1]
        S = max(min(self.slots, total + n_carry), 2)
        F, I = ly.zeros(S, dev)
        if n_carry:  # the carried slots first (the working set grows to hold them if it must)
            Fc, Ic = carry
            self._count(Ic, -1)  # their work before this run was counted by the run that carried them out
            if n_carry > S:
                F, I = ly.zeros(n_carry, dev)
            F[:, :n_carry], I[:, :n_carry] = Fc, Ic
        next_id, calls = 0, 0
        fusable = self.fusable
        while True:
            if calls % REFILL_EVERY == 0:
                t_rf = time.perf_counter()
                free = self._free(I)
                S = I.shape[1]
                # Once the queue is empty, harvest only to compact or to finish: the tail's calls are short, and
                # a harvest (a few dozen small ops) costs more than a step there.
                due = True
                if next_id >= total:
                    n_free = int(free.sum())
                    due = (n_free == S or (S - n_free < COMPACT_BELOW * S and S > MIN_SLOTS)
                           or (fusable and S - n_free <= TAIL_SLOTS) or keep is not None)
                if due:
                    idx = free.nonzero().squeeze(1)
                    k = 0
                    if len(idx):
                        self._retire(F, I, idx, acc, on_done)
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
                        return None
                    if next_id >= total:
                        if keep is not None and self._only_kept(I, keep):
                            tm["refill"] += time.perf_counter() - t_rf
                            return self._carry_out(F, I)
                        if fusable and live <= TAIL_SLOTS:
                            tm["refill"] += time.perf_counter() - t_rf
                            if on_tail is not None:
                                on_tail()
                            return self._tail(F, I, acc, on_done, keep)
                        if live < COMPACT_BELOW * S and S > MIN_SLOTS:
                            F, I = self._compact(F, I, MIN_SLOTS)
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

    def _only_kept(self, I: Tensor, keep: Callable[[Tensor], Tensor], free: Tensor | None = None) -> bool:
        """Every slot with a path in flight is one ``keep`` lets the run leave behind (``free``: ``_free(I)``, when
        the caller has it)."""
        free = self._free(I) if free is None else free
        return not bool((~free & ~keep(I)).any())

    def _carry_out(self, F: Tensor, I: Tensor) -> tuple[Tensor, Tensor] | None:
        """The live slots, to go on in a later run (their work so far counted in this one)."""
        live = (~self._free(I)).nonzero().squeeze(1)
        if not len(live):
            return None
        Fc, Ic = F[:, live].contiguous(), I[:, live].contiguous()
        self._count(Ic, 1)
        return Fc, Ic

    def _compact(self, F: Tensor, I: Tensor, floor: int) -> tuple[Tensor, Tensor]:
        """The live slots, padded with idle ones to at least ``floor`` (dynamic-shape kernels specialise 0 and 1)."""
        free = self._free(I)
        keep = (~free).nonzero().squeeze(1)
        if len(keep) < floor:  # pad with idle slots
            keep = torch.cat([keep, free.nonzero().squeeze(1)[: floor - len(keep)]])
        return F[:, keep].contiguous(), I[:, keep].contiguous()

    def _tail(self, F: Tensor, I: Tensor, acc: Tensor, on_done: Callable[[int], None] | None,
              keep: Callable[[Tensor], Tensor] | None) -> tuple[Tensor, Tensor] | None:
        """The last live slots (the queue is empty, at most :data:`TAIL_SLOTS` live): runs of
        :data:`TAIL_CALLS` fused calls (a tracking step and the vertices it reaches, :meth:`Machine.advance`), then,
        once more than :data:`TAIL_FREE` of the slots are free, a harvest and a compaction. A path takes the same
        steps with the same draws as in the driver's main loop; only when its slot is harvested differs. The
        collector's :meth:`~nrc.render.wavefront.program.Collector.after_advance` runs after each call until
        :meth:`~nrc.render.wavefront.program.Collector.after_advance_ahead` says no live slot needs it."""
        c, tm, ly, col = self.counts, self.timers, self.layout, self.collector
        F, I = self._compact(F, I, 2)
        ahead = col.after_advance_ahead(ly, I)
        while True:
            t_st = time.perf_counter()
            for _ in range(TAIL_CALLS):
                F, I = self.machine.advance(F, I, self.inputs)
                if ahead:
                    col.after_advance(ly, F, I)
            S = I.shape[1]
            c["iterations"] += TAIL_CALLS
            c["tail_calls"] = c.get("tail_calls", 0) + TAIL_CALLS
            c["slot_steps"] += S * TAIL_CALLS
            t_rf = time.perf_counter()
            tm["tail"] = tm.get("tail", 0.0) + t_rf - t_st
            free = self._free(I)
            n_free = int(free.sum())
            kept = keep is not None and self._only_kept(I, keep, free)
            # a harvest costs ~20 fused calls (NRC's: more): finished slots wait in the working set (a few tenths
            # of a µs a call each) until a quarter of it is free, then leave it in one harvest and a compaction
            if n_free == S or kept or (n_free > TAIL_FREE * S and S > 2):
                idx = free.nonzero().squeeze(1)
                self._retire(F, I, idx, acc, on_done)
                if n_free == S:
                    tm["refill"] += time.perf_counter() - t_rf
                    return None
                if kept:
                    tm["refill"] += time.perf_counter() - t_rf
                    return self._carry_out(F, I)
                F, I = self._compact(F, I, 2)
                ahead = ahead and col.after_advance_ahead(ly, I)
            tm["refill"] += time.perf_counter() - t_rf

    def _finish(self, acc: Tensor) -> None:
        """Trace what the queues still hold and add their counters."""
        c, tm = self.counts, self.timers
        if self.shadow is not None:
            self.shadow.flush(acc)
            c["shadow_rays"] += self.shadow.done
            tm["shadow"] = self.shadow.seconds
        if self.equiangular is not None:
            self.equiangular.flush(acc)
            c["equiangular_segments"] = self.equiangular.done
            tm["equiangular"] = self.equiangular.seconds
