"""``renderer=nrc``: neural radiance caching, rendered frame after frame like a real-time renderer.

Each frame (``frames`` in the root config):

1. **trace** (:mod:`nrc.render.radiance_caching.paths`): ``spp`` render paths per pixel, terminated into the cache by
   ``renderer.termination``, and one self-training path per training pixel, in one wavefront;
2. **infer** (:mod:`nrc.render.radiance_caching.inference_filter`): the cache (EMA weights, as trained up to the previous
   frame) is queried at every termination, in batches of ``inference.batch_size`` query slots; batches
   without a query are skipped;
3. **train**: training targets by the backward recurrence (:mod:`nrc.render.radiance_caching.training_set`), the batch
   filter (``batch_filter`` group) picks the batches of the training image to train, invalid records are
   replaced from the ring buffer of earlier frames, one Adam step per batch, then the frame's valid
   records enter the ring buffer (:mod:`nrc.render.radiance_caching.trainer`; with ``renderer.training.overlap``
   beside the next frame's trace, its ``loss`` then logged with the next frame, ``FrameLog.trained``).

The output is the last frame's image, or the mean over frames with ``renderer.accumulate``. With a
``renderer.reference`` EXR every frame's relative MSE is logged. A checkpoint (cache weights, Adam, EMA,
ring buffer, accumulation, history; :mod:`nrc.render.radiance_caching.checkpoint`) is written to
``checkpoint.pt`` in the run directory at the end, after a SIGINT or SIGTERM (the current frame is finished
first; a second signal stops at once), and every 60 s of rendering (``checkpoint_every: auto``) or every N
frames; ``renderer.resume=<path>`` continues from one of the same configuration, and because every frame
draws from its own generator seeded by ``(seed, frame)`` a resumed run continues the loss curve and the
image exactly as the uninterrupted run would have.

Non-finite values are counted, never hidden: cache predictions that are NaN/Inf (treated as 0 radiance) per
frame in ``nonfinite_predictions``; training steps with a non-finite loss or gradient are skipped before
Adam and the EMA (``cache_skipped_steps``); :data:`MAX_NONFINITE_STEPS` of them in a row stop the run with
a message (the checkpoint on disk stays the last good one).
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf
from torch import Tensor
from tqdm import tqdm

from nrc.cache.radiance_cache import build_radiance_cache
from nrc.camera import Camera
from nrc.errors import ConfigError, NRCError
from nrc.render.radiance_caching import debias
from nrc.render.radiance_caching.checkpoint import (CheckpointError, check_config, load_checkpoint, plain,
                                                    save_checkpoint)
from nrc.render.radiance_caching.frame_log import LIGHT_SCALARS, FrameLog, load_reference
from nrc.render.radiance_caching.inference_filter import filtered_query
from nrc.render.radiance_caching.paths import NRCPathTracer, PathSet
from nrc.render.radiance_caching.ring_buffer import RingBuffer, TrainingRecords
from nrc.render.radiance_caching.settings import NRCRendererSettings, resolve_auto, ring_size
from nrc.render.radiance_caching.signals import StopOnSignal
from nrc.render.radiance_caching.trainer import Trainer, TrainingJob
from nrc.render.radiance_caching.training_set import (frame_records, training_positions,
                                                      training_targets)
from nrc.render.result import RenderResult
from nrc.render.reuse import make_reuse
from nrc.render.wavefront.machine import compiled_graphs
from nrc.scene import Scene, animated_scene, turned_suns
from nrc.transport.light_sampling import LightSampler
from nrc.transport.rng import RandomSource

FrameOut = tuple[int, np.ndarray, np.ndarray, dict[str, Any]]  # frame, image, output, stats
FrameCallback = Callable[[int, np.ndarray, np.ndarray, dict[str, Any]], None]


MAX_NONFINITE_STEPS = 8  # consecutive skipped (non-finite) training steps that stop a run
logger = logging.getLogger("nrc")


class NRCRenderer:
    """The NRC frame loop (see the module docstring).

    Args:
        scene: the validated scene.
        settings: everything it reads, typed (:class:`~nrc.render.radiance_caching.settings.NRCRendererSettings`;
            :func:`nrc.render.registry.make_renderer` builds them from the app config); ``auto`` rules not yet
            resolved are resolved for ``scene`` here (:func:`~nrc.render.radiance_caching.settings.resolve_auto`).
        cache: a radiance cache to use instead of building one from the settings (tests inject stubs).
    """

    name = "nrc"

    def __init__(self, scene: Scene, settings: NRCRendererSettings, cache: Any = None) -> None:
        settings = resolve_auto(settings, scene)  # a no-op on the settings the entry points hand over
        self.config = settings  # the whole settings; self.settings: their renderer block (NRCSettings)
        self.scene = scene
        self.device = scene.device
        self.settings = st = settings.nrc
        self.frames, self.display, self.batch_filter = settings.frames, settings.display, settings.batch_filter
        tr = st.training
        self.medium_mask = settings.medium_mask  # (H, W) bool: the flicker figure's pixels (resolve_auto's)
        self.medium_pixels = int(self.medium_mask.sum())
        self.optical_depth = settings.optical_depth  # the median over the camera rays, when an auto rule needed it
        if cache is None and settings.cache is None:
            raise ConfigError("renderer=nrc builds its cache from the config groups cache, encoding, extra_inputs")
        # the hash table sized to the training paths in a thick cloud (encoding.position.log2_hashmap_size: auto)
        groups = settings.cache
        self.cache = cache if cache is not None else build_radiance_cache(
            groups.cache, groups.encoding, groups.extra_inputs, scene.grid, self.device, scene.integrator.seed,
            training_paths=tr.n_paths, thick=settings.regime == "thick", animated=st.animate != "none",
            lights=scene.lights)
        if st.cuda_graphs and hasattr(self.cache, "use_graphs"):  # the training step's forward and backward too
            self.cache.use_graphs()
        self.train_order = self.batch_filter.order(tr.height, tr.width, self.device)
        self.ring = RingBuffer(ring_size(tr, self.medium_pixels / scene.camera.num_pixels, st.animate), self.device)
        self.trainer = Trainer(self.cache, self.ring, tr.records_per_path)
        self.transmittance = settings.transmittance
        self.tracer = NRCPathTracer(scene, self.transmittance, st)
        self.reuse = make_reuse(st.reuse, scene.g, scene.integrator.spp, scene.grid, scene.albedo)
        self.tracer.frames = self.frames
        self.lights = st.light_sampling.sampler(scene)
        self.reference = load_reference(st.reference, scene.camera)  # (H, W, 3) or None: rel_mse per frame
        self.out_dir: Path | None = None
        self.tensorboard_dir: Path | None = None
        self.config_yaml = settings.config_yaml
        self.checkpoint_path: Path | None = None
        self.checkpoint_frame, self.checkpoint_bytes = 0, 0
        self.interrupted: int | None = None
        self._skipped_seen = 0

    def attach_output(self, out_dir: Path) -> None:
        """The run directory: TensorBoard logs (``tensorboard/``) and ``checkpoint.pt`` go there."""
        self.out_dir = Path(out_dir)

    # ------------------------------------------------------------------ per-frame scene state
    def frame_camera(self, frame: int) -> Camera:
        """The camera of ``frame`` (:func:`nrc.scene.animated_scene`: it orbits with ``animate.mode=orbit``)."""
        return animated_scene(self.scene, self.settings.animate, self.settings.degrees_per_frame, frame).camera

    def frame_lights(self, frame: int) -> LightSampler:
        """The lights of ``frame`` (:func:`nrc.scene.animated_scene`: the directional lights turn with
        ``animate.mode=sun``)."""
        if self.settings.animate != "sun" or frame == 0:
            return self.lights
        return self.lights.with_lights(turned_suns(self.lights.lights, self.settings.degrees_per_frame * frame))

    # ------------------------------------------------------------------ one frame
    def frame_rng(self, frame: int) -> RandomSource:
        """The random numbers of ``frame``: a generator seeded by ``(integrator.seed, frame)``."""
        return RandomSource.seeded(self.scene.integrator.seed * 1_000_003 + frame, self.device)

    def render_frame(self, frame: int) -> tuple[Tensor, dict[str, Any], list[float]]:
        """Trace, infer and train one frame; returns its image ``(H, W, 3)``, its statistics and the losses."""
        st, scene, tr = self.settings, self.scene, self.settings.training
        rng = self.frame_rng(frame)
        camera = self.frame_camera(frame)
        t0 = time.perf_counter()
        offset = rng.rand(1, 2)[0]
        train_xy = training_positions(self.train_order, tr.width, tr.height, camera.width, camera.height, offset)
        unbiased = rng.rand(tr.n_paths, 1)[:, 0] < tr.unbiased_fraction_at(frame)
        ps = PathSet(camera, scene.integrator.spp, train_xy, unbiased, frame)
        lights = self.frame_lights(frame)
        q = st.debias.probability
        trainer = self.trainer
        trace = self.tracer.trace(ps, lights, rng, q, on_tail=trainer.start)
        reuse_stats: dict[str, Any] = {}
        if self.reuse is not None:  # the render paths' first-vertex direct light, by reservoir reuse
            contribution, reuse_stats = self.reuse.frame(trace.reuse, camera, lights, self.transmittance,
                                                         scene.grid, self.tracer.core.majorants, rng.generator,
                                                         st.shadow_batch)
            pix = torch.div(torch.arange(ps.n_render, device=self.device), ps.spp, rounding_mode="floor")
            trace.acc.index_add_(0, pix, contribution)
        t1 = time.perf_counter()
        trainer.join()  # the previous frame's training (overlap), before the cache is read
        if hasattr(self.cache, "inputs"):  # the light-depth input follows the frame's lights (unchanged: nothing done)
            self.cache.inputs.set_lights(lights.lights)
        t1j = time.perf_counter()

        # Training paths' terminal queries read the raw weights (training.query_weights=raw; a cache without
        # separate raw weights, such as a test stub, answers them with query).
        query_from = getattr(self.cache, "query_raw", None) if tr.query_weights == "raw" else None
        values, infer_counts = filtered_query(self.cache.query, trace.query_x, trace.query_d, trace.query_pid,
                                              ps.n_render + trace.pool.n_paths, st.inference_batch, query_from,
                                              ps.n_render)
        # Radiance is never negative: a linear output that dips below 0 (early frames) would otherwise
        # darken the image and, through self-training, feed negative targets back into the cache.
        nonfinite = int((~torch.isfinite(values)).any(dim=-1).sum()) if values.numel() else 0
        values = torch.nan_to_num(values, nan=0.0, posinf=0.0).clamp(min=0.0)
        acc = trace.acc
        acc.index_add_(0, trace.query_dest, trace.query_w * values)
        debias_stats: dict[str, Any] = {}
        if st.debias.enabled:  # the continued paths' suffixes: the cache as a control variate (debias.py)
            debias_stats = debias.apply(trace, values, ps.spp, q)
        n_pix = trace.n_pixels
        image = (acc[:n_pix] / ps.spp).reshape(camera.height, camera.width, 3)
        if not bool(torch.isfinite(image).all()):
            bad = int((~torch.isfinite(image)).any(dim=-1).sum())
            raise NRCError(f"frame {frame}: {bad} pixels of the NRC image are NaN/Inf (the path tracing part "
                           "diverged; the image is not written)")
        if st.debias.enabled:  # unbiased frames can have negative pixels; they are kept (counted here)
            debias_stats["debias_negative_pixels"] = int((image < 0).any(dim=-1).sum())
        t2 = time.perf_counter()

        records, valid, late = self._frame_records(trace, frame)
        mask = torch.zeros(tr.n_paths, dtype=torch.bool, device=self.device)
        mask[self.train_order] = trace.scattered | trace.in_flight[trace.pool.tids(frame)]
        batches = self.batch_filter.batches(mask.view(tr.height, tr.width))
        suffix = None
        if st.debias.enabled and st.debias.train_on_suffixes:  # unbiased suffixes: more records for later batches
            suffix = debias.suffix_records(trace, q)
        n_valid = int(valid.sum())
        job = TrainingJob(frame, records, valid, torch.full((len(valid),), frame, dtype=torch.long,
                                                            device=self.device),
                          late, batches, suffix, rng.generator)
        # trained now, or beside the next frame's trace (where it has the one-thread tail: trainer.py)
        trainer.submit(job, overlap=tr.overlap and self.device.type == "cpu" and trace.fused_tail)
        losses, train_work, _ = trainer.done.pop(frame, ([], None, False))
        t3 = time.perf_counter()

        # time_train_s: what the frame waited for training (its records, its steps run here or the wait for the
        # second thread); time_train_work_s: its steps' own time, wherever they ran. With overlap, loss,
        # train_steps and time_train_work_s come with the next frame (FrameLog.trained).
        stats: dict[str, Any] = {
            "time_trace_s": t1 - t0, "time_infer_s": t2 - t1j, "time_train_s": (t1j - t1) + (t3 - t2),
            "time_train_work_s": train_work, "time_frame_s": t3 - t0,
            "loss": float(np.mean(losses)) if losses else None, "nonfinite_predictions": nonfinite,
            "train_steps": len(losses), "train_beside_trace": False, "train_batches": len(batches),
            "train_records_valid": n_valid,
            "training_pixels_scattering": int(trace.scattered.sum()),
            **self._carry_stats(trace, frame),
            **{f"time_{k}_s": v for k, v in trace.timers.items()}, **trace.counts, **infer_counts,
            **{k: v for k, v in st.light_sampling.metrics(lights).items() if k in LIGHT_SCALARS}, **reuse_stats,
            **debias_stats,
        }
        return image, stats, losses

    def _frame_records(self, trace: Any, frame: int) -> tuple[TrainingRecords, Tensor, tuple | None]:
        """``(records, valid, late)``: the records of ``frame``'s own training paths in training-image order (a
        path still in flight: invalid, filled from the ring buffer), and ``(records, valid, started frames)`` of
        the paths of earlier frames that ended in this one (``None``: none). Targets by the backward recurrence
        over each ended path's rows (:func:`training_targets`)."""
        pool, V, dev = trace.pool, self.settings.training.records_per_path, self.device
        fin = trace.finished.nonzero().squeeze(1)
        ridx = (fin[:, None] * V + torch.arange(V, device=dev)).reshape(-1)
        rows = trace.acc[trace.n_pixels + ridx]
        albedo = self.scene.albedo
        if trace.direct is None:
            targets = training_targets(rows, len(fin), V, albedo)
        else:  # cache_target=indirect: each record's own direct light stays out of its target
            direct = trace.direct[ridx]
            targets = training_targets(rows + direct, len(fin), V, albedo) - direct
        recs, ok = frame_records(pool.rec_x[ridx], pool.rec_d[ridx], targets, pool.rec_valid[ridx])
        own = pool.tids(frame)
        mine = (ridx >= own.start * V) & (ridx < own.stop * V)
        n = pool.n_train * V
        records = TrainingRecords(*(torch.zeros(n, 3, device=dev) for _ in range(3)))
        valid = torch.zeros(n, dtype=torch.bool, device=dev)
        pos = ridx[mine] - own.start * V
        for dst, src in zip(records, recs):
            dst[pos] = src[mine]
        valid[pos] = ok[mine]
        late = None
        if not bool(mine.all()):
            other = ~mine
            started = pool.started[pool.block_of(ridx[other] // V)]
            late = (TrainingRecords(*(f[other] for f in recs)), ok[other], started)
        return records, valid, late

    @staticmethod
    def _carry_stats(trace: Any, frame: int) -> dict[str, Any]:
        """The training paths carried across frames: in flight at the frame's end, ended in this frame after their
        own (and their mean delay in frames), aged at its start (in their last frame: they end into the cache at their
        next vertex) and dropped there (older than ``carry_frames``)."""
        pool = trace.pool
        own = pool.tids(frame)
        late = trace.finished.clone()
        late[own] = False
        n_late = int(late.sum())
        delay = None
        if n_late:
            delay = float((frame - pool.started[pool.block_of(late.nonzero().squeeze(1))]).float().mean())
        return {"training_paths_in_flight": int(trace.in_flight.sum()), "training_paths_late": n_late,
                "training_late_frames": delay, "training_paths_aged": trace.aged,
                "training_paths_dropped": trace.dropped}

    def _check_training(self, frame: int, stats: dict[str, Any]) -> None:
        """Warn about non-finite predictions and skipped steps; stop a cache that keeps diverging."""
        if stats.get("nonfinite_predictions"):
            logger.warning("frame %d: %d cache predictions were NaN/Inf (counted as 0 radiance)", frame,
                        stats["nonfinite_predictions"])
        skipped = getattr(self.cache, "n_skipped_steps", 0)
        if skipped > self._skipped_seen:
            logger.warning("frame %d: %d training steps skipped (non-finite loss or gradient; weights untouched)",
                        frame, skipped - self._skipped_seen)
            self._skipped_seen = skipped
        if getattr(self.cache, "n_consecutive_skipped", 0) >= MAX_NONFINITE_STEPS:
            kept = (f"the last good checkpoint is {self.checkpoint_path} (frame {self.checkpoint_frame})"
                    if self.checkpoint_path is not None else "no checkpoint was written")
            raise NRCError(f"frame {frame}: the radiance cache's training loss was NaN/Inf for "
                           f"{MAX_NONFINITE_STEPS} steps in a row; stopped ({kept})")

    # ------------------------------------------------------------------ checkpoints
    def _checkpoint(self, path: Path, frame: int, accum: Tensor, n_accum: int, log: FrameLog) -> None:
        try:
            self.checkpoint_bytes = save_checkpoint(path, {
                "frame": frame, "cache": self.cache.state_dict(), "ring": self.ring.state_dict(),
                "accum": accum.cpu(), "n_accum": n_accum, "history": plain(log.history),
                "reuse": self.reuse.state_dict() if self.reuse is not None else None,
                "pool": self.tracer.pool_state(),
                "config": self.config_yaml})
        except OSError as exc:
            raise NRCError(f"cannot write the checkpoint {path}: {exc.strerror or exc}") from None
        self.checkpoint_path, self.checkpoint_frame = path, frame

    def _resume(self, path: str, log: FrameLog) -> tuple[int, Tensor, int]:
        state = load_checkpoint(path, self.device)
        if self.config_yaml:
            check_config(path, state["config"], OmegaConf.create(self.config_yaml))
        try:
            self.cache.load_state_dict(state["cache"])
            self.ring.load_state_dict(state["ring"])
        except (RuntimeError, KeyError, ValueError) as exc:
            if isinstance(exc, ConfigError):
                raise
            raise CheckpointError(f"renderer.resume: {path} does not fit this cache "
                                  f"({str(exc).splitlines()[0]})") from None
        accum = state["accum"].to(self.device)
        cam = self.scene.camera
        if tuple(accum.shape) != (cam.height, cam.width, 3):
            raise CheckpointError(f"renderer.resume: {path} holds a {accum.shape[1]}x{accum.shape[0]} image, the "
                                  f"camera renders {cam.width}x{cam.height}")
        log.load(state["history"])
        frame = int(state["frame"])
        tr = self.settings.training
        try:  # the training paths in flight, carried on exactly as the uninterrupted run does
            self.tracer.load_pool(state.get("pool"), cam.num_pixels * self.scene.integrator.spp, tr.n_paths)
        except (ValueError, KeyError, RuntimeError) as exc:
            raise CheckpointError(f"renderer.resume: {path} does not fit this renderer's training paths "
                                  f"({str(exc).splitlines()[0]})") from None
        if self.reuse is not None:  # the reservoirs of the last frame done, seen by its camera
            self.reuse.load_state_dict(state.get("reuse"), self.frame_camera(frame - 1), self.device)
        return frame, accum, int(state["n_accum"])

    def _flicker(self, output: torch.Tensor, previous: torch.Tensor | None) -> float | None:
        """Mean ``|output - previous|`` over the pixels that see the medium and the channels, over the mean of the
        reference there (of ``output`` without a reference); ``None`` for the first frame. metrics.json's
        ``flicker`` is its mean over the second half of the frames (a static camera: the cache's own change and
        noise; with ``renderer.animate`` it includes the motion)."""
        from nrc.metrics import flicker

        if previous is None or not bool(self.medium_mask.any()):
            return None
        pair = torch.stack([previous, output]).cpu().numpy()
        ref = self.reference if self.reference is not None else pair[1]
        try:
            return flicker(pair, ref, self.medium_mask.cpu().numpy())
        except ValueError:  # black over the medium: no scale to measure against
            return None

    # ------------------------------------------------------------------ the frame loop
    def _log_trained(self, log: FrameLog, step: int) -> int:
        """Log the steps of the frames trained after they were logged (``renderer.training.overlap``); returns the
        next step's number."""
        for f, (losses, seconds, beside) in sorted(self.trainer.take().items()):
            log.trained(f, step, losses, seconds, beside)
            step += len(losses)
        return step

    def render(self, progress: bool = False, on_frame: FrameCallback | None = None) -> RenderResult:
        """Run ``frames`` frames (:meth:`frame_loop`, a SIGINT or SIGTERM stopping it after the current frame);
        ``on_frame(frame, image, output, stats)`` is called after each."""
        with StopOnSignal() as stop:
            loop = self.frame_loop(progress, stop)
            try:
                while True:
                    try:
                        item = next(loop)
                    except StopIteration as end:
                        return end.value
                    if on_frame is not None:
                        on_frame(*item)
            finally:
                loop.close()  # left on an error of on_frame: the loop closes its training thread first

    def frame_loop(self, progress: bool = False,
                   stop: StopOnSignal | None = None) -> Generator[FrameOut, None, RenderResult]:
        """The frame loop, in the caller's thread: yields ``(frame, image, output, stats)`` after each frame and
        returns the run's :class:`RenderResult`; closing it early stops the run after
        the frame yielded (``nrc.frames``). ``stop``: the signal handler that ends it after a frame (none: inert)."""
        stop = stop if stop is not None else StopOnSignal(active=False)
        st, cam = self.settings, self.scene.camera
        log_dir = self.out_dir / "tensorboard" if (self.out_dir is not None and st.tensorboard) else None
        if log_dir is not None and st.resume is not None:  # continue the interrupted run's curves, in its own logs
            earlier = Path(st.resume).parent / "tensorboard"
            if earlier.is_dir() and os.access(earlier, os.W_OK):
                log_dir = earlier
        self.tensorboard_dir = log_dir
        log = FrameLog(log_dir, st.image_every, self.display)
        accum = torch.zeros(cam.height, cam.width, 3, device=self.device)
        start, n_accum = 0, 0
        if st.resume is not None:
            start, accum, n_accum = self._resume(st.resume, log)
            if start >= self.frames:
                raise ConfigError(f"renderer.resume: the checkpoint is at frame {start}, frames={self.frames}")
        step = sum(log.history.get("train_steps", []))
        output = accum
        previous = None  # the last frame's output (the flicker figure)
        t_start = t_saved = time.perf_counter()
        done = start
        self.interrupted = None
        try:
            for frame in tqdm(range(start, self.frames), disable=not progress, desc="nrc", unit="frame",
                              leave=False):
                image, stats, losses = self.render_frame(frame)
                step = self._log_trained(log, step)  # the previous frame's steps, taken beside this trace
                self._check_training(frame, stats)
                if st.accumulate:
                    accum += image
                    n_accum += 1
                    output = accum / n_accum
                else:
                    output = image
                stats["flicker"] = self._flicker(output, previous)
                stats["lr_mlp"] = getattr(self.cache, "mlp_lr", None)  # the MLP's rate after the frame's steps so far
                previous = output.clone()
                out_np = output.cpu().numpy()
                if self.reference is not None:
                    from nrc.metrics import mse, rel_mse

                    stats["rel_mse"] = rel_mse(out_np, self.reference)
                    stats["mse"] = mse(out_np, self.reference)
                log.steps(step, losses)
                step += len(losses)
                last = frame == self.frames - 1 or stop.signal is not None  # the final frame is always logged
                log.frame(frame, stats, {"frame": image.cpu().numpy(), "output": out_np}, force_images=last)
                yield frame, image.cpu().numpy(), out_np, stats
                done = frame + 1
                stop.frame_done = True
                if stop.signal is not None:
                    self.interrupted = stop.signal
                    break
                waited = time.perf_counter() - t_saved
                by_time = st.checkpoint_seconds is not None and waited >= st.checkpoint_seconds
                due = (st.checkpoint_every and done % st.checkpoint_every == 0) or by_time
                if self.out_dir is not None and due and done < self.frames:
                    self.trainer.join()  # this frame's steps first: the checkpoint holds no job half done
                    step = self._log_trained(log, step)
                    self._checkpoint(self.out_dir / "checkpoint.pt", done, accum, n_accum, log)
                    t_saved = time.perf_counter()
        except BaseException:  # a render left on an error or early (nrc.frames) leaves no training thread behind
            self.trainer.close()
            raise
        elapsed = time.perf_counter() - t_start
        self.trainer.join()  # the last frame's steps
        self.trainer.close()
        self._log_trained(log, step)
        if self.out_dir is not None and done > start:
            self._checkpoint(self.out_dir / "checkpoint.pt", done, accum, n_accum, log)
        log.close()
        h = log.history
        metrics: dict[str, Any] = {
            "renderer": self.name, "frames": self.frames, "first_frame": start, "spp": self.scene.integrator.spp,
            "accumulate": st.accumulate, "transmittance": self.transmittance.name,
            "termination": st.termination.rule, "cache_target": st.cache_target, "time_frames_s": elapsed,
            "tensorboard_dir": str(self.tensorboard_dir) if self.tensorboard_dir is not None else None,
            **st.light_sampling.metrics(self.lights), **st.reuse.metrics(self.scene.g), **st.debias.metrics(),
            "shadow_rays": int(sum(h.get("shadow_rays", []))),
            "equiangular_segments": int(sum(h.get("equiangular_segments", []))),
            "training_image": [st.training.width, st.training.height], "training_auto": st.training.auto,
            "unbiased_fraction": st.training.unbiased_fraction,
            "unbiased_warmup_frames": st.training.unbiased_warmup_frames, "carry_frames": st.training.carry_frames,
            "training_overlap": st.training.overlap,  # the setting; frames whose steps ran beside the next trace:
            "train_beside_trace": int(sum(h.get("train_beside_trace", []))),
            "optical_depth_median": self.optical_depth,
            "medium_pixels": self.medium_pixels, "ring_buffer": self.ring.capacity,
            "backend": self.tracer.backend, "backend_requested": st.backend, "backend_reason": self.tracer.backend_reason,
            "compiled_graphs_in_process": compiled_graphs() if self.tracer.backend == "compiled" else None,
            "cuda_graphs": self.tracer.graph_report,
            "training_graphs": getattr(self.cache, "graph_report", None),
            "cache_parameters": self.cache.n_parameters if hasattr(self.cache, "n_parameters") else None,
            "cache_log2_hashmap_size": getattr(self.cache, "log2_hashmap_size", None),
            "cache_steps": getattr(self.cache, "n_steps", None),
            # the MLP's learning-rate schedule (cache.optimizer.lr_final_fraction, auto resolved) and its rate now
            "cache_lr_final_fraction": getattr(getattr(self.cache, "settings", None), "lr_final_fraction", None),
            "cache_mlp_lr": getattr(self.cache, "mlp_lr", None),
            "cache_skipped_steps": getattr(self.cache, "n_skipped_steps", None),
            "training_backend": getattr(self.cache, "training_backend", None),
            "training_backend_reason": getattr(self.cache, "training_backend_reason", None),
            "nonfinite_predictions": int(sum(h.get("nonfinite_predictions", []))),
            "frames_done": done, "interrupted": signal.Signals(self.interrupted).name if self.interrupted else None,
            "checkpoint": str(self.checkpoint_path) if self.checkpoint_path else None,
            "checkpoint_frame": self.checkpoint_frame, "checkpoint_bytes": self.checkpoint_bytes,
            "frame_times_s": h.get("time_frame_s", []), "time_trace_s": h.get("time_trace_s", []),
            "time_infer_s": h.get("time_infer_s", []), "time_train_s": h.get("time_train_s", []),
            "loss_per_frame": h.get("loss", []), "history": h,
        }
        changes = [x for x in h.get("flicker", []) if x is not None]
        metrics["flicker"] = float(np.mean(changes[len(changes) // 2:])) if changes else None
        if self.reference is not None:
            metrics["final_rel_mse"] = h["rel_mse"][-1]
            metrics["final_mse"] = h["mse"][-1]
        return RenderResult(image=output.cpu().numpy(), metrics=metrics)
