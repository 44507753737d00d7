"""The cache's training on a frame's records: at the frame's end, or beside the next frame's trace.

A frame's training (:class:`TrainingJob`) is the frame's records (its own training paths' and those of earlier frames
that ended in it), the batches the batch filter picked and the frame's generator. :class:`Trainer` runs it:

* at once, after the frame's inference, on every thread: ``renderer.training.overlap=false``, a GPU, or a trace
  without the one-thread tail (the eager backend's structure);
* else (``overlap``, the CPU, the compiled structure) on a second thread with one intra-op thread, started when the
  next frame's trace reaches its one-thread tail (:meth:`nrc.render.wavefront.driver.Wavefront.run`'s ``on_tail``;
  one core finishes the last paths, the other trains), or when that trace ends without one, or before a checkpoint
  (:meth:`Trainer.join`); the next frame's inference waits for it.

Either way the cache, Adam and the ring buffer see the same updates in the same order: frame ``f``'s inference reads
the weights trained on the records of frames ``< f``, since a trace reads neither the cache nor the ring buffer.
Only the thread count of the arithmetic differs, so the two modes agree within float tolerance, not bit for bit;
each is deterministic for a fixed seed, and because an overlapped job always runs on the second thread, wherever it
starts, a checkpoint (written after :meth:`Trainer.join`) resumes exactly.

Off by default: on 2 cores the overlapped frame was no faster (the two threads, both Python loops of short ops, wait
on each other for the interpreter lock; docs/measurements/nrc_frames.md, "Training beside the tail; fused calls; the training
budget").
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.radiance_caching.ring_buffer import RingBuffer, TrainingRecords


@dataclass
class TrainingJob:
    """One frame's training: ``records`` ``V`` per training path in training-image order (``valid``: the usable ones,
    ``started``: the frame each record's path started in), ``late`` ``(records, valid, started)`` of earlier frames'
    paths that ended in ``frame`` (or ``None``), the ``batches`` (training-path ranges ``[a, b)``), the debiased
    suffixes' records (``suffix``, or ``None``) and ``gen``, the frame's generator (the ring buffer's draws for invalid
    records come from it; nothing else draws from it once the job is made: every frame has its own)."""

    frame: int
    records: TrainingRecords
    valid: Tensor
    started: Tensor
    late: tuple[TrainingRecords, Tensor, Tensor] | None
    batches: list[tuple[int, int]]
    suffix: tuple[TrainingRecords, Tensor] | None
    gen: torch.Generator


class Trainer:
    """Runs the :class:`TrainingJob` s of the frames on ``cache`` (``train_step``) with ``ring`` filling their invalid
    records; ``V`` records per training path.

    Per frame: :meth:`start` (the trace's ``on_tail``), :meth:`join` after the trace, then :meth:`submit` the frame's
    own job. What each job did waits in :attr:`done` (``{frame: (losses, seconds, beside)}``, ``beside``: it started
    while a trace was still running) for :meth:`take` (or its own frame's entry, popped). The second thread is made
    on first use and lives as long as the trainer, or until :meth:`close`."""

    def __init__(self, cache: Any, ring: RingBuffer, V: int) -> None:
        self.cache, self.ring, self.V = cache, ring, V
        self.pending: TrainingJob | None = None
        self.done: dict[int, tuple[list[float], float, bool]] = {}
        self._future: Future | None = None
        self._beside = False
        self._pool: ThreadPoolExecutor | None = None

    def start(self, beside: bool = True) -> None:
        """Start the waiting job on the second thread (a no-op when none waits or it has started); ``beside``: a
        trace is still running."""
        if self.pending is not None and self._future is None:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="nrc-train", initializer=torch.set_num_threads,
                                                initargs=(1,))
            self._future = self._pool.submit(self.run, self.pending)
            self._beside = beside

    def join(self) -> None:
        """Finish the waiting job (started on the second thread now if it has not started)."""
        if self.pending is None:
            return
        self.start(beside=False)
        job, future = self.pending, self._future
        self.pending, self._future = None, None
        self.done[job.frame] = (*future.result(), self._beside)

    def submit(self, job: TrainingJob, overlap: bool) -> None:
        """A frame's job: kept for the next frame's trace (``overlap``) or run now, here."""
        if self.pending is not None:
            raise RuntimeError("Trainer.submit: the previous frame's job has not been joined")
        if overlap:
            self.pending = job
        else:
            self.done[job.frame] = (*self.run(job), False)

    def close(self) -> None:
        """End the second thread (after the job it runs, whose outcome is dropped: a render that stops on an error
        or early); a later :meth:`start` makes a new one."""
        if self._future is not None:
            self._future.exception()  # waits; an error of its own is the render's to report, not this one's
            self.pending, self._future = None, None
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def take(self) -> dict[int, tuple[list[float], float, bool]]:
        """Remove and return what the finished jobs did."""
        done, self.done = self.done, {}
        return done

    def run(self, job: TrainingJob) -> tuple[list[float], float]:
        """Train ``job`` and return its losses and seconds: late records into its batches' holes, one Adam step per
        batch (invalid records drawn from the ring buffer), then its valid records (and suffixes) into the ring
        buffer."""
        t0 = time.perf_counter()
        V, gen = self.V, job.gen
        if job.late is not None:
            self._place_late(job)
        losses = []
        for a, b in job.batches:
            batch = self.ring.fill(TrainingRecords(*(f[a * V:b * V] for f in job.records)), job.valid[a * V:b * V],
                                   gen)
            losses.append(self.cache.train_step(*batch))
        self.ring.push(job.records, job.valid, job.started)
        if job.suffix is not None:
            self.ring.push(*job.suffix, job.frame)
        return losses, time.perf_counter() - t0

    def _place_late(self, job: TrainingJob) -> None:
        """Records of training paths of earlier frames that ended in this one (``late``): in order, into the
        invalid records of the frame's trained batches (mostly this frame's paths still in flight, which take the
        late paths' place: each late record is trained once, directly, as it would have been in its own frame);
        the rest into the ring buffer, before the batches draw from it. The job's ``records``, ``valid`` and
        ``started`` are updated in place."""
        lrec, lok, lstart = job.late
        V, valid = self.V, job.valid
        in_batch = torch.zeros_like(valid)
        for a, b in job.batches:
            in_batch[a * V:b * V] = True
        holes = (~valid & in_batch).nonzero().squeeze(1)
        lv = lok.nonzero().squeeze(1)
        k = min(len(holes), len(lv))
        for dst, src in zip(job.records, lrec):
            dst[holes[:k]] = src[lv[:k]]
        valid[holes[:k]] = True
        job.started[holes[:k]] = lstart[lv[:k]]
        rest = lv[k:]
        if len(rest):
            self.ring.push(TrainingRecords(*(f[rest] for f in lrec)), torch.ones(len(rest), dtype=torch.bool,
                                                                                   device=valid.device), lstart[rest])
