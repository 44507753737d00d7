"""``renderer=pt``: the reference volumetric path tracer (batched wavefront, unbiased).

Estimator (per camera sample; SCENE.md conventions):

* Free flights by delta tracking against the brick majorants (one global majorant with
  ``renderer.free_flight=global``), bricks with a zero majorant crossed in one step; at a real collision the
  path scatters (throughput x albedo), up to ``integrator.max_scatter`` real scattering events.
* Next-event estimation at every real scattering vertex: one light chosen (``renderer.light_selection``:
  uniformly, by power, or by resampling ``renderer.ris.candidates`` power samples by their unshadowed
  contribution, RIS) among the scene's lights, its transmittance by ratio tracking inside the step
  (``transmittance=ratio``) or by the configured estimator on queued batches of ``renderer.shadow_batch`` rays.
  Environment light is also gathered by phase-sampled directions that escape the box, combined with NEE by the
  power heuristic (camera rays that escape see the environment with weight 1).
* With ``renderer.point_light_sampling=equiangular`` the point lights leave the vertices' next-event estimate:
  their direct light is estimated along every flight segment by equi-angular distance sampling
  (:mod:`nrc.transport.equiangular`).
* Optional Russian roulette on the throughput (off by default).
* With ``renderer.reuse.mode`` ``spatial`` or ``spatiotemporal`` the image is rendered as ``spp`` passes of one
  sample per pixel (sample ``j`` of every pixel in pass ``j``, the same paths as without reuse), and the first
  vertex's next-event estimate of each pass is made by reservoir reuse across the pass's pixels and, for
  ``spatiotemporal``, from the previous pass (a static camera: :mod:`nrc.render.reuse`).

Execution: the shared transport core (:mod:`nrc.render.wavefront`) -- the same step code for
``renderer.backend=eager`` and ``compiled`` (``auto`` chooses, see :mod:`nrc.render.wavefront.setup`). A fixed
working set of ``renderer.slots`` paths is refilled from the queue of camera samples; peak memory is the
state (156 bytes a slot, 10 MB at 65,536 slots), the shadow queue and the ``(H x W x 3)`` image, independent of
image size and spp. Random numbers are counter-based per (seed, sample id, step): the image does not depend
on the slot count.
"""

from __future__ import annotations

import logging
import math
import os
import time
from typing import Any

from dataclasses import dataclass, replace

import torch
from tqdm import tqdm

from nrc.config import ConfigReader
from nrc.render.result import RenderResult
from nrc.render.wavefront import BACKENDS, build_core, camera_paths
from nrc.render.reuse import ReuseSettings, VertexRecord, make_reuse
from nrc.render.wavefront.driver import Queues, Wavefront
from nrc.render.wavefront.machine import compiled_graphs
from nrc.render.wavefront.program import Collector, VertexProgram
from nrc.render.wavefront.step import RussianRoulette
from nrc.scene import Scene
from nrc.transport.light_sampling import LightSamplingSettings
from nrc.transport.rng import path_key, uniforms
from nrc.transport.transmittance import DEFAULT_ESTIMATOR, Transmittance, make_transmittance

log = logging.getLogger(__name__)

__all__ = ["BACKENDS", "PathTracer", "PathTracerSettings"]


@dataclass(frozen=True)
class PathTracerSettings:
    """The validated ``renderer`` block of ``renderer=pt``. Every default lives in ``conf/renderer/pt.yaml`` and
    ``conf/renderer/shared/wavefront.yaml`` (read here as required keys); unknown keys are errors naming the key."""

    slots: int
    """Paths in flight (the working set); memory grows linearly with it (156 bytes a slot)."""
    shadow_batch: int
    """Queued next-event rays traced per estimator call (eager, or estimators without a per-step form)."""
    brick: int | str
    """Majorant-grid brick edge in voxels, or ``auto`` (sized to the medium's density)."""
    free_flight: str
    """Delta-tracking majorant: ``brick`` or ``global``."""
    russian_roulette: bool
    """Throughput roulette on."""
    rr_start: int
    """First scattering event at which the roulette may stop a path."""
    rr_max_survival: float
    """Survival probability cap of the roulette (``q = min(clamp(max throughput, 0.05, 1), max_survival)``;
    Mitsuba 3: 0.95); below 1 it stops albedo-1 paths too (:class:`nrc.render.wavefront.step.RussianRoulette`)."""
    backend: str
    """``auto`` | ``eager`` | ``compiled`` (:mod:`nrc.render.wavefront.setup`)."""
    compile_min_samples: int
    """``auto`` with a cold cache: renders of fewer camera samples stay eager."""
    steps_per_call: int
    """Tracking steps unrolled per compiled call."""
    cuda_graphs: bool
    """The step's calls through CUDA graphs of padded slot buckets (``device=cuda`` only;
    :mod:`nrc.render.wavefront.graphs`)."""
    light_sampling: LightSamplingSettings = LightSamplingSettings()
    """How lights are sampled: ``light_selection`` (``uniform`` | ``power`` | ``ris``), ``ris.candidates``,
    ``point_light_sampling`` (``none`` | ``equiangular``) (nrc.transport.light_sampling)."""
    reuse: ReuseSettings = ReuseSettings()
    """``reuse.mode`` (``none`` | ``spatial`` | ``spatiotemporal``), ``neighbors``, ``radius``, ``history``,
    ``defer_g``, ``target``, ``mis``, ``domain`` (``light`` | ``distance``), ``distance_candidates``,
    ``distance_steps``: reservoir
    reuse at the first vertex or along the camera ray (nrc.render.reuse)."""
    transmittance: Transmittance = Transmittance(DEFAULT_ESTIMATOR)
    """The shadow rays' transmittance estimator (the root ``transmittance`` group; :meth:`from_app_config`)."""

    @property
    def roulette(self) -> RussianRoulette | None:
        """The throughput roulette the core runs (``None``: off)."""
        return RussianRoulette(self.rr_start, self.rr_max_survival) if self.russian_roulette else None

    @property
    def inline_shadows(self) -> bool:
        """Compiled, with ratio tracking: shadow rays inside the step (:func:`nrc.render.wavefront.build_core`)."""
        return True

    @classmethod
    def from_config(cls, renderer: Any) -> PathTracerSettings:
        cfg = ConfigReader(renderer, "renderer")
        cfg.get_choice("name", ["pt"])
        settings = cls(
            slots=cfg.get_int("slots", lo=1),
            shadow_batch=cfg.get_int("shadow_batch", lo=1),
            brick=cfg.get_raw("brick"),  # 'auto' or an edge, validated by wavefront_majorants
            free_flight=cfg.get_choice("free_flight", ["brick", "global"]),
            russian_roulette=(rr := RussianRoulette.from_config(cfg))[0],  # read in key order
            rr_start=rr[1].start,
            rr_max_survival=rr[1].max_survival,
            backend=cfg.get_choice("backend", list(BACKENDS)),
            compile_min_samples=cfg.get_int("compile_min_samples", lo=0),
            steps_per_call=cfg.get_int("steps_per_call", lo=1),
            cuda_graphs=cfg.get_bool("cuda_graphs"),
            light_sampling=LightSamplingSettings.from_config(cfg),
            reuse=ReuseSettings.from_config(cfg),
        )
        cfg.finish()
        return settings

    @classmethod
    def from_app_config(cls, cfg: Any) -> PathTracerSettings:
        """From the app config: the ``renderer`` block and the ``transmittance`` group."""
        return replace(cls.from_config(cfg.renderer), transmittance=make_transmittance(cfg.get("transmittance")))


class PathTracer:
    """The wavefront path tracer (see module docstring).

    Args:
        scene: the validated scene (its ``integrator`` block: spp, seed, max_scatter).
        settings: its typed settings, passed whole (:meth:`PathTracerSettings.from_app_config`;
            :func:`nrc.render.registry.make_renderer` builds them from the app config).
    """

    name = "pt"

    def __init__(self, scene: Scene, settings: PathTracerSettings) -> None:
        self.settings = st = settings
        self.scene = scene
        self.device = scene.device
        self.slots, self.shadow_batch = st.slots, st.shadow_batch
        self.free_flight, self.backend, self.steps_per_call = st.free_flight, st.backend, st.steps_per_call
        self.transmittance = st.transmittance
        self.lights = st.light_sampling.sampler(scene)
        self.spp = scene.integrator.spp
        self.max_scatter = scene.integrator.max_scatter
        self.core = build_core(scene, self.transmittance, st, VertexProgram(hooks=st.reuse.hooks(scene.g)))
        self.majorants = self.core.majorants

    def _camera_paths(self, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Packed camera paths for sample ids (``pixel = id // spp``); the jitter is the path's draw 0."""
        key = path_key(self.scene.integrator.seed, ids)
        pix = torch.div(ids, self.spp, rounding_mode="floor")
        jitter = torch.stack(uniforms(key, torch.zeros_like(key), 2), dim=1)
        return camera_paths(self.core.step.layout, self.scene.camera, self.scene.grid, pix, jitter, key)

    def render(self, progress: bool = False, on_pass: Any = None) -> RenderResult:
        """Render the scene; ``metrics`` name the backend (and why), the start-up (compile or cache load)
        apart from ``time_render_s``, and the work counters. With reuse, ``on_pass(j, image (H, W, 3))`` gets
        each 1-spp pass's own image."""
        cam = self.scene.camera
        total = cam.num_pixels * self.spp
        machine, backend, reason = self.core.choose(total)
        image = torch.zeros(cam.num_pixels, 3, device=self.device)
        gen = torch.Generator(device=self.device).manual_seed(self.scene.integrator.seed)
        bar = tqdm(total=total, unit="sample", unit_scale=True, disable=not progress, desc="pt", leave=False,
                   mininterval=1.0)
        start = time.perf_counter()
        reuse_stats: dict[str, list] = {}
        wf = self._render_passes(machine, gen, image, bar, on_pass, reuse_stats)
        elapsed = time.perf_counter() - start
        bar.close()
        img = (image / self.spp).reshape(cam.height, cam.width, 3)
        if not bool(torch.isfinite(img).all()):
            raise RuntimeError("path tracer produced non-finite pixels")
        metrics: dict[str, Any] = {
            "renderer": self.name,
            "backend": backend,
            "backend_requested": self.backend,
            "backend_reason": reason,
            "free_flight": self.free_flight,
            "brick": self.majorants.brick,
            "transmittance": self.transmittance.name,
            "spp": self.spp,
            "samples": total,
            "slots": self.slots,
            "steps_per_call": self.steps_per_call,
            "cuda_graphs": machine.graph_report,
            "time_compile_s": self.core.last_startup_s,  # spent by this render (0 when the process had it)
            "compile_cache_hit": machine.cache_hit if backend == "compiled" else None,
            "compile_cache_dir": os.environ.get("TORCHINDUCTOR_CACHE_DIR") if backend == "compiled" else None,
            "compiled_graphs_in_process": compiled_graphs() if backend == "compiled" else None,
            "time_render_s": elapsed,
            "samples_per_second": total / elapsed if elapsed > 0 else math.inf,
            **{f"time_{k}_s": v for k, v in wf.timers.items()},
            **wf.counts,
            **self.settings.light_sampling.metrics(self.lights),
            **self.settings.reuse.metrics(self.scene.g),
            **{k: (sum(v) if k in ("reuse_vertices", "time_reuse_s") else sum(v) / len(v)) for k, v in reuse_stats.items()},
        }
        return RenderResult(image=img.cpu().numpy(), metrics=metrics)

    def _wavefront(self, machine: Any, gen: torch.Generator, record: VertexRecord | None = None) -> Wavefront:
        """A wavefront of the core's machine with its shadow and equi-angular queues (drawing from ``gen``);
        ``record``: the reuse vertices are recorded into it."""
        queues = Queues(self.core.shadow_queue(machine, self.shadow_batch, gen),
                        self.core.equiangular_queue(self.shadow_batch, gen))
        return Wavefront(machine, self.core.inputs, self.lights, self.slots, queues, Collector(watchers=(record,)))

    def trace_pass(self, machine: Any, gen: torch.Generator, record: VertexRecord | None, j: int, passes: int,
                   out: torch.Tensor) -> Wavefront:
        """Pass ``j`` of ``passes`` one-sample passes (sample ``pixel * passes + j`` of every pixel) traced into
        ``out`` (``(pixels, 3)``, added to) on ``machine`` (``self.core.choose``), recording the reuse vertices into
        ``record``: what a reuse render does before its reuse pass (``scripts/bench_reuse.py`` decomposes it)."""
        wf = self._wavefront(machine, gen, record)
        wf.run(self.scene.camera.num_pixels, lambda r: self._camera_paths(r * passes + j), out)
        return wf

    def _render_passes(self, machine: Any, gen: torch.Generator, image: torch.Tensor, bar: Any, on_pass: Any,
                       stats: dict[str, list]) -> Wavefront:
        """The render: one pass of every sample, or with reuse ``spp`` passes of one sample per pixel (module
        docstring), each followed by the reuse pass; returns the last pass's wavefront with the counters of all."""
        cam, spp, st, g = self.scene.camera, self.spp, self.settings, self.scene.g
        n = cam.num_pixels
        reuse = make_reuse(st.reuse, g, 1, self.scene.grid, self.scene.albedo)
        passes = 1 if reuse is None else spp
        counts: dict[str, int] = {}
        timers: dict[str, float] = {}
        wf = None
        for j in range(passes):
            rec = st.reuse.record(n, g, self.scene.albedo, self.device)
            wf = self._wavefront(machine, gen, rec)
            if reuse is None:
                wf.run(n * spp, self._camera_paths, image, on_done=bar.update)
                return wf
            one = torch.zeros_like(image)
            wf.run(n, lambda r, j=j: self._camera_paths(r * spp + j), one, on_done=bar.update)
            contribution, s = reuse.frame(rec, cam, self.lights, self.transmittance, self.scene.grid,
                                          self.majorants, gen, self.shadow_batch)
            one += contribution
            image += one
            if on_pass is not None:
                on_pass(j, one.reshape(cam.height, cam.width, 3))
            for k, v in s.items():
                stats.setdefault(k, []).append(v)
            for k, v in wf.counts.items():
                counts[k] = counts.get(k, 0) + v
            for k, v in wf.timers.items():
                timers[k] = timers.get(k, 0.0) + v
        wf.counts, wf.timers = counts, timers
        return wf
