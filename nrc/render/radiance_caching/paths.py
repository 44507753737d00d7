"""One wavefront for the NRC renderer's render paths and self-training paths.

Render paths (``spp`` per pixel) and training paths (one per training pixel) are traced in the same working set of
``slots`` paths by the path tracer's transport core (:mod:`nrc.render.wavefront`, eager or compiled). The NRC part
of the step is its vertex (:mod:`nrc.render.radiance_caching.vertex`): the termination rule
(:mod:`nrc.render.radiance_caching.termination`), the training records and the cache query. A terminating path
adds ``beta x cache(x_m, d_m)`` (``beta`` its throughput before ``x_m``'s albedo, ``d_m`` the direction arriving
at ``x_m``); with ``cache_target=indirect`` also its own next-event estimate (``terminal_nee``: light sampling, the
uniform sky's direction by the sky or the phase function). Training paths
go on ``extra_vertices`` past that vertex (a fraction ``unbiased_fraction`` never terminates), and vertex ``j`` of
one becomes a record ``(x_j, d_j) -> T_j`` with ``T_j = acc_j + albedo x T_{j+1}``. With ``renderer.reuse`` the
render paths' reuse vertex is recorded for the reuse pass (:mod:`nrc.render.reuse`); with ``renderer.debias`` a
terminating render path may go on as a path-traced suffix (:mod:`nrc.render.radiance_caching.debias`). What the
cache stores, the targets and the termination rules: ``docs/nrc.md``, "One frame".

Contributions land in one accumulator ``acc`` of ``P + N_train x V + 1`` rows: rows ``[0, P)`` are image
pixels (sums over the ``spp`` samples), then ``V`` rows per training path, then one discard row for
training paths that have not scattered yet; with ``cache_target=indirect`` then ``N_train x V`` rows of the
records' own direct light; with ``renderer.debias`` then one suffix row per render sample (zero unless the
sample was continued; the caller adds them to the pixels). Cache queries are returned (not evaluated) so the
caller can batch and filter them. Everything is float32.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from nrc.camera import Camera
from nrc.transport.rng import RandomSource
from nrc.render.radiance_caching.settings import NRCSettings
from nrc.render.radiance_caching.vertex import NRCCollector, NRCVertex
from nrc.render.wavefront import build_core, camera_paths
from nrc.render.wavefront.driver import Queues, Wavefront
from nrc.scene import Scene
from nrc.transport.light_sampling import LightSampler
from nrc.transport.rng import path_key


@dataclass
class PathSet:
    """The paths of one frame: ``spp`` render samples per pixel, then one path per training pixel.

    Attributes:
        camera: the frame's camera.
        spp: render samples per pixel.
        train_xy: ``(N_train, 2)`` image-plane positions of the training paths in pixel units
            (``x`` right in ``[0, W)``, ``y`` down in ``[0, H)``).
        train_unbiased: ``(N_train,)`` bool, training paths that never terminate into the cache.
    """

    camera: Camera
    spp: int
    train_xy: Tensor
    train_unbiased: Tensor
    frame: int = 0
    """The frame (its training paths take the pool's block ``frame % blocks``, :class:`TrainingPool`)."""

    @property
    def n_render(self) -> int:
        return self.camera.num_pixels * self.spp

    @property
    def n_train(self) -> int:
        return int(self.train_xy.shape[0])


class TrainingPool:
    """The training paths' records across frames (``renderer.training.carry_frames`` = k).

    A frame's training paths take block ``frame % (k + 1)`` of the pool: training path ``k`` of the frame is pool
    path ``tid = block * n_train + k`` (its cache query's slot ``n_render + tid``), and owns the accumulator rows
    and records ``[tid V, (tid + 1) V)``. A frame stops when its render paths are done; its training paths that
    are still going are carried (:attr:`carry`, their packed slots) into the next frame's wavefront and end there
    or later, with their rows intact. In the last frame a path may go on in (``k`` frames after its own) it ends
    into the cache at its next vertex (:meth:`start`, "aged"); a block is reused ``k + 1`` frames later, and a path
    of its earlier frame still going then (one that met no vertex in that frame) is dropped: its records never
    count. ``k = 0``: one block, and a frame waits for its training paths.

    Memory: ``(k + 1) n_train V`` records (positions, directions, validity, and in the accumulator the radiance
    rows, twice with ``cache_target=indirect``), ``(k + 1) n_train`` flags, and the carried slots (at most
    ``(k + 1) n_train``, bounded by the renderer's ``slots``).
    """

    def __init__(self, n_train: int, V: int, blocks: int, device: torch.device) -> None:
        self.n_train, self.V, self.blocks, self.device = n_train, V, blocks, device
        n = blocks * n_train
        self.rec_x = torch.zeros(n * V, 3, device=device)
        self.rec_d = torch.zeros(n * V, 3, device=device)
        self.rec_valid = torch.zeros(n * V, dtype=torch.bool, device=device)
        self.scattered = torch.zeros(n, dtype=torch.bool, device=device)  # the path had a real collision
        self.finished = torch.zeros(n, dtype=torch.bool, device=device)  # the path has ended (its records complete)
        self.started = torch.full((blocks,), -1, dtype=torch.long, device=device)  # each block's frame (-1: none)
        self.carry: tuple[Tensor, Tensor] | None = None  # the slots in flight (packed F, I)

    @property
    def n_paths(self) -> int:
        return self.blocks * self.n_train

    def block(self, frame: int) -> int:
        return frame % self.blocks

    def block_of(self, tids: Tensor) -> Tensor:
        """The block of each pool path ``tids`` (so ``started[block_of(tids)]`` is the frame it started in)."""
        return torch.div(tids, self.n_train, rounding_mode="floor")

    def tids(self, frame: int) -> slice:
        """The pool paths of ``frame``'s training paths."""
        b = self.block(frame)
        return slice(b * self.n_train, (b + 1) * self.n_train)

    def in_flight(self, layout: Any) -> Tensor:
        """``(n_paths,)`` bool: the pool paths carried in flight."""
        out = torch.zeros(self.n_paths, dtype=torch.bool, device=self.device)
        if self.carry is not None:
            out[self.carry[1][layout.i("rec_base")] // self.V] = True
        return out

    def start(self, frame: int, layout: Any, acc_rows: list[Tensor]) -> tuple[int, int]:
        """Free ``frame``'s block for its new training paths and age the carried ones; returns ``(dropped, aged)``.

        Dropped: the carried paths still in flight from the block's earlier frame (``k + 1`` frames old; rare: see
        aged). Aged: the carried paths entering the last frame they may go on in (``k`` frames old, the block the
        next frame reuses) end into the cache at their next vertex, as a self-training path does: a long path is
        cut short, not removed, so the records do not lose the longest paths (dropping them would train the cache
        on the paths that end early alone, a bias towards the light that escapes soon). Clears the block's
        records, flags and accumulator rows (``acc_rows``: views of the pool's rows in the accumulator,
        ``(n_paths V, 3)`` each)."""
        b, V = self.block(frame), self.V
        dropped = aged = 0
        if self.carry is not None:
            Fc, Ic = self.carry
            block = self.block_of(Ic[layout.i("rec_base")] // V)
            mine = block == b
            dropped = int(mine.sum())
            if dropped:
                keep = (~mine).nonzero().squeeze(1)
                self.carry = (Fc[:, keep].contiguous(), Ic[:, keep].contiguous()) if len(keep) else None
                block = block[keep]
            if self.carry is not None:  # what is left (with one block, nothing: all were this block's)
                Ic = self.carry[1]
                old = block == self.block(frame + 1)
                aged = int(old.sum())
                if aged:  # n_term: the vertex at which the path terminates into the cache (0: undecided)
                    n, n_term = Ic[layout.i("n")], Ic[layout.i("n_term")]
                    soon = n + 1
                    Ic[layout.i("n_term")] = torch.where(old & ((n_term == 0) | (n_term > soon)), soon, n_term)
        t = self.tids(frame)
        r = slice(t.start * V, t.stop * V)
        for rows in acc_rows:
            rows[r] = 0.0
        self.rec_valid[r] = False
        self.scattered[t] = False
        self.finished[t] = False
        self.started[b] = frame
        return dropped, aged

    def state_dict(self) -> dict[str, Any]:
        return {"rec_x": self.rec_x.cpu(), "rec_d": self.rec_d.cpu(), "rec_valid": self.rec_valid.cpu(),
                "scattered": self.scattered.cpu(), "finished": self.finished.cpu(), "started": self.started.cpu(),
                "carry": [t.cpu() for t in self.carry] if self.carry is not None else None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("rec_x", "rec_d", "rec_valid", "scattered", "finished", "started"):
            mine = getattr(self, name)
            if tuple(state[name].shape) != tuple(mine.shape):
                raise ValueError(f"training pool {name} is {tuple(state[name].shape)}, expected {tuple(mine.shape)}")
            mine.copy_(state[name].to(mine.device))
        carry = state.get("carry")
        self.carry = tuple(t.to(self.device) for t in carry) if carry is not None else None


@dataclass
class FrameTrace:
    """What tracing a :class:`PathSet` produced (see the module docstring for ``acc``'s layout).

    ``query_*`` are the cache terminations: position, unit direction of travel, weight ``(Q, 3)``,
    destination row of ``acc`` and the id of the path (render samples ``0..P*spp-1`` in pixel order,
    then training paths). ``direct`` (``cache_target=indirect`` only) is each record's own direct light, kept out
    of its ``acc`` row. ``rec_*`` are ``(N_train * V, ...)``: record position, direction and whether
    the vertex exists and is not terminal. ``scattered[k]``: training path ``k`` had a real collision.
    """

    acc: Tensor
    n_pixels: int
    query_x: Tensor
    query_d: Tensor
    query_w: Tensor
    query_dest: Tensor
    query_pid: Tensor
    rec_x: Tensor
    rec_d: Tensor
    rec_valid: Tensor
    scattered: Tensor
    counts: dict[str, int] = field(default_factory=dict)
    timers: dict[str, float] = field(default_factory=dict)
    direct: Tensor | None = None  # cache_target=indirect: (pool paths * V, 3) each record's direct light
    pool: TrainingPool | None = None  # the training pool (rows, records and flags of every block)
    finished: Tensor | None = None  # (pool paths,) bool: the pool paths that ended in this frame
    in_flight: Tensor | None = None  # (pool paths,) bool: carried into the next frame
    dropped: int = 0  # carried paths dropped at this frame's start (older than carry_frames)
    aged: int = 0  # carried paths in their last frame at its start: they end into the cache at their next vertex
    fused_tail: bool = False  # the wavefront's structure has the one-thread tail (Wavefront.fusable)
    reuse: Any = None  # the render paths' reuse vertices (reuse.VertexRecord; None without reuse)
    # renderer.debias: (n_render, 3) each render sample's suffix row (a view of acc; zero where not continued),
    # query_cont (Q,) the queries of continued paths, whose (sample id, throughput at the vertex) are cont_pid,
    # cont_beta in the same order
    suffix: Tensor | None = None
    query_cont: Tensor | None = None
    cont_pid: Tensor | None = None
    cont_beta: Tensor | None = None


class NRCPathTracer:
    """Traces the render and training paths of a frame (see the module docstring).

    Args:
        scene: the validated scene (medium, albedo, g, ``integrator.max_scatter``).
        transmittance: the shadow-ray estimator (``make_transmittance``).
        settings: the renderer's settings, passed whole (:class:`~nrc.render.radiance_caching.settings.NRCSettings`,
            its training image already sized): the termination rule, the training records per path and suffix
            length, the unbiased training paths' cap, slots and shadow batch, the majorants, the execution backend,
            the cache target, light sampling, the reuse vertex, ``debias`` and the throughput roulette (it only
            reaches the paths that go on past ``start`` vertices: unbiased training paths and ``renderer.debias``
            suffixes).
    """

    def __init__(self, scene: Scene, transmittance: object, settings: NRCSettings) -> None:
        st, tr = settings, settings.training
        self.scene = scene
        self.settings = st
        self.device = scene.device
        self.transmittance = transmittance
        self.V = tr.records_per_path
        self.extra_vertices = tr.extra_vertices
        self.slots = st.slots
        self.shadow_batch = st.shadow_batch
        self.cache_target = st.cache_target
        self.debias = st.debias.enabled  # renderer.debias: render paths may go on past their cache termination (q per frame)
        # the vertex program (termination rule, training records, debias; reservoir reuse's hook)
        self.program = NRCVertex(st, hooks=st.reuse.hooks(scene.g))
        self._cores: dict = {}
        self.core = self._core(RandomSource.counter_uniforms)
        self.frames = 1  # frames the renderer will trace (backend=auto weighs a compile against all of them)
        self.backend: str | None = None
        self.backend_reason: str | None = None
        self._machine: Any = None  # the last frame's machine
        self.carry_frames = tr.carry_frames  # frames a training path may go on past its own (TrainingPool)
        self.pool: TrainingPool | None = None
        self._pool_render = 0
        self._pool_rows: list[Tensor] | None = None  # a checkpoint's pool rows, until the accumulator exists
        self._acc: Tensor | None = None  # the accumulator, kept across frames (the pool's rows)

    @property
    def graph_report(self) -> dict[str, Any] | None:
        """``renderer.cuda_graphs`` as the last frame's machine ran it (:attr:`Machine.graph_report`)."""
        return self._machine.graph_report if self._machine is not None else None

    def _core(self, uniforms):
        if uniforms not in self._cores:
            self._cores[uniforms] = build_core(self.scene, self.transmittance, self.settings, self.program, uniforms)
            self._cores[uniforms].warm_fraction = 1 / 12  # see Core.warm_fraction
        return self._cores[uniforms]

    # ------------------------------------------------------------------ new paths
    def _new_paths(self, ids: Tensor, ps: PathSet, rng: RandomSource, layout, discard: int,
                   first_tid: int) -> tuple[Tensor, Tensor]:
        """Packed new paths for ids; training path ``k`` is pool path ``first_tid + k`` and accumulates into
        ``discard`` until its first vertex."""
        cam, dev = ps.camera, self.device
        n = len(ids)
        key = path_key(rng.seed, ids)
        is_train = ids >= ps.n_render
        k = (ids - ps.n_render).clamp(min=0)
        jitter = torch.stack(rng.counter_uniforms(key, torch.zeros_like(key), 2), dim=1)
        pix = torch.div(ids, ps.spp, rounding_mode="floor")
        if ps.n_train:
            xy = ps.train_xy[k.clamp(max=ps.n_train - 1)]
            col = xy[:, 0].floor().clamp(0, cam.width - 1)
            row = xy[:, 1].floor().clamp(0, cam.height - 1)
            pix = torch.where(is_train, row.long() * cam.width + col.long(), pix)
            jitter = torch.where(is_train[:, None], (xy - torch.stack([col, row], 1)).clamp(0.0, 1.0 - 2**-24), jitter)
            never = is_train & ps.train_unbiased[k.clamp(max=ps.n_train - 1)]
        else:
            never = torch.zeros(n, dtype=torch.bool, device=dev)
        F, I = camera_paths(layout, cam, self.scene.grid, pix, jitter, key)
        F[layout.f("x_prev")] = F[layout.f("o")]
        tid = first_tid + k
        I[layout.i("rec")] = -1
        I[layout.i("dest")] = torch.where(is_train, discard, pix)
        I[layout.i("pid")] = torch.where(is_train, ps.n_render + tid, ids)
        I[layout.i("extra")] = torch.where(is_train, self.extra_vertices, 0)
        I[layout.i("never")] = never.long()
        I[layout.i("rec_base")] = torch.where(is_train, tid * self.V, -1)
        return F, I

    def pool_for(self, n_render: int, n_train: int) -> TrainingPool:
        """The training pool for these path counts (a new, empty one when they changed)."""
        pool = self.pool
        if pool is None or pool.n_train != n_train or self._pool_render != n_render:
            pool = self.pool = TrainingPool(n_train, self.V, self.carry_frames + 1, self.device)
            self._pool_render = n_render
            self._acc = None
        return pool

    # ------------------------------------------------------------------ main loop
    def trace(self, ps: PathSet, lights: LightSampler, rng: RandomSource, debias_q: float = 0.0,
              on_tail: Callable[[], None] | None = None) -> FrameTrace:
        """Trace every path of ``ps`` and the training paths carried from earlier frames; NEE lands in ``acc``,
        cache terminations are returned as queries (``debias_q``: the probability that a render path goes on past
        its cache termination, with ``renderer.debias``; in ``(0, 1]``). ``on_tail()``: called once, when the
        wavefront's last slots go on in one thread (:meth:`nrc.render.wavefront.driver.Wavefront.run`).

        ``acc`` (see the module docstring) persists across frames: its pixel, discard and suffix rows are cleared
        each frame, a pool block's rows when the block is started (:class:`TrainingPool`)."""
        dev, V = self.device, self.V
        core = self._core(rng.counter_uniforms)
        pool = self.pool_for(ps.n_render, ps.n_train)
        n_pixels = ps.camera.num_pixels
        total = ps.n_render + ps.n_train
        n_rec = pool.n_paths * V
        discard = n_pixels + n_rec
        indirect = self.cache_target == "indirect"
        n_rows = discard + 1 + (n_rec if indirect else 0)
        suffix_base = n_rows if self.debias else None
        if self.debias:
            if not 0.0 < debias_q <= 1.0:
                raise ValueError(f"debias_q must be in (0, 1], got {debias_q}")
            n_rows += ps.n_render
        if self._acc is None or self._acc.shape[0] != n_rows:
            self._acc = torch.zeros(n_rows, 3, device=dev)
            if self._pool_rows is not None:  # the pool's rows of a resumed run (load_pool)
                self._acc[n_pixels:n_pixels + n_rec] = self._pool_rows[0]
                if indirect:
                    self._acc[discard + 1:discard + 1 + n_rec] = self._pool_rows[1]
                self._pool_rows = None
        acc = self._acc
        acc[:n_pixels] = 0.0
        acc[discard:discard + 1] = 0.0
        if suffix_base is not None:
            acc[suffix_base:] = 0.0
        machine, self.backend, self.backend_reason = core.choose(total * self.frames)
        self._machine = machine
        layout = machine.step.layout
        pool_rows = [acc[n_pixels:discard]] + ([acc[discard + 1:discard + 1 + n_rec]] if indirect else [])
        dropped, aged = pool.start(ps.frame, layout, pool_rows)
        finished_before = pool.finished.clone()
        rec = self.settings.reuse.record(ps.n_render, self.scene.g, self.scene.albedo, dev)
        hv = NRCCollector(n_pixels, ps.n_render, V, pool.rec_x, pool.rec_d, pool.rec_valid, pool.scattered,
                          discard + 1 if indirect else None, debias_q=debias_q if self.debias else 0.0,
                          suffix_base=suffix_base, watchers=(rec,), finished=pool.finished)
        queues = Queues(core.shadow_queue(machine, self.shadow_batch, rng.generator),
                        core.equiangular_queue(self.shadow_batch, rng.generator))
        frame = {"debias_q": debias_q} if self.debias else {}
        wf = Wavefront(machine, core.inputs_for(lights, **frame), lights, self.slots, queues, hv)
        first_tid = pool.tids(ps.frame).start
        i_rec = layout.i("rec_base")
        keep = (lambda I: I[i_rec] >= 0) if self.carry_frames else None  # training paths may go on later
        pool.carry = wf.run(total, lambda ids: self._new_paths(ids, ps, rng, layout, discard, first_tid), acc,
                            carry=pool.carry, keep=keep, on_tail=on_tail)
        counts = dict(wf.counts)
        timers = {"trace_" + k: v for k, v in wf.timers.items()}
        timers["compile"] = core.last_startup_s

        def cat(name: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
            q = hv.queries[name]
            return torch.cat(q) if q else torch.zeros(shape, dtype=dtype, device=dev)

        counts["cache_queries"] = sum(len(v) for v in hv.queries["pid"])
        debias = {}
        if self.debias:
            debias = dict(suffix=acc[suffix_base:], query_cont=cat("cont", (0,), torch.bool),
                          cont_pid=torch.cat(hv.continued["pid"]) if hv.continued["pid"] else
                          torch.zeros(0, dtype=torch.long, device=dev),
                          cont_beta=torch.cat(hv.continued["beta"]) if hv.continued["beta"] else
                          torch.zeros(0, 3, device=dev))
        tids = pool.tids(ps.frame)
        return FrameTrace(
            acc=acc, n_pixels=n_pixels,
            query_x=cat("x", (0, 3), torch.float32), query_d=cat("d", (0, 3), torch.float32),
            query_w=cat("w", (0, 3), torch.float32), query_dest=cat("dest", (0,), torch.long),
            query_pid=cat("pid", (0,), torch.long), rec_x=pool.rec_x[tids.start * V:tids.stop * V],
            rec_d=pool.rec_d[tids.start * V:tids.stop * V], rec_valid=pool.rec_valid[tids.start * V:tids.stop * V],
            scattered=pool.scattered[tids], counts=counts, timers=timers,
            direct=acc[discard + 1:discard + 1 + n_rec] if indirect else None, reuse=rec, pool=pool,
            finished=pool.finished & ~finished_before, in_flight=pool.in_flight(layout), dropped=dropped, aged=aged,
            fused_tail=wf.fusable, **debias,
        )

    # ------------------------------------------------------------------ checkpoints
    def pool_state(self) -> dict[str, Any] | None:
        """The training pool with its accumulator rows (the carried paths' partial sums), for a checkpoint."""
        pool, acc = self.pool, self._acc
        if pool is None or acc is None:
            return None
        n_pixels, n_rec = self._pool_render // self.scene.integrator.spp, pool.n_paths * self.V
        rows = [acc[n_pixels:n_pixels + n_rec].cpu()]
        if self.cache_target == "indirect":
            rows.append(acc[n_pixels + n_rec + 1:n_pixels + 2 * n_rec + 1].cpu())
        return {**pool.state_dict(), "rows": rows, "n_render": self._pool_render}

    def load_pool(self, state: dict[str, Any] | None, n_render: int, n_train: int) -> None:
        """Restore :meth:`pool_state` (``None``: an empty pool, e.g. a checkpoint of an older nrc: the paths that
        were in flight are lost, a documented difference from the uninterrupted run)."""
        self.pool, self._acc, self._pool_rows = None, None, None
        pool = self.pool_for(n_render, n_train)
        if state is None:
            return
        if int(state["n_render"]) != n_render:
            raise ValueError(f"the checkpoint's frames have {state['n_render']} render paths, this one {n_render}")
        pool.load_state_dict(state)
        self._pool_rows = [r.to(self.device) for r in state["rows"]]
