"""Setting up the transport core for a renderer: majorants, the step's structure, scene inputs, the backend.

``renderer.backend`` (``pt`` and ``nrc``): ``eager`` runs the step as plain PyTorch ops; ``compiled`` runs the
same step ``torch.compile``'d; ``auto`` compiles when this process already holds the compiled step, when the
persistent cache holds its AOT packages (a load of milliseconds, on the CPU), when it holds torch.compile's kernels
and the work repays their load of seconds (``warm_fraction`` of ``compile_min_samples``), or when the work is large
enough to repay a cold compile (``compile_min_samples`` camera samples); otherwise eager. Which backend ran and why is
in the metrics (``backend``, ``backend_reason``, ``time_compile_s``, ``compile_cache_hit``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.errors import ConfigError, failure_line
from nrc.render.wavefront.driver import EquiangularQueue, ShadowQueue
from nrc.render.wavefront.machine import (Machine, SceneInputs, compiled_machine_ready, is_cached, machine_for,
                                          packages_cached)
from nrc.render.wavefront.program import VertexProgram
from nrc.render.wavefront.state import FLIGHT, Layout
from nrc.render.wavefront.step import StepOptions, Transport, Uniforms
from nrc.transport.equiangular import EquiangularSampler
from nrc.transport.light_sampling import LightSampler
from nrc.transport.rng import uniforms as counter_uniforms
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import BrickTables, MajorantGrid

log = logging.getLogger(__name__)

BACKENDS = ("auto", "eager", "compiled")


def wavefront_majorants(grid: DensityGrid, brick: Any, free_flight: str) -> tuple[MajorantGrid, MajorantGrid]:
    """``(majorants, tracking_majorants)`` from ``renderer.brick`` / ``renderer.free_flight``.

    ``brick`` is ``'auto'`` (:meth:`MajorantGrid.auto_brick`) or an edge in voxels; shadow rays always use
    these brick majorants. Free flights use them too (``free_flight='brick'``) or one majorant for the whole
    box (``'global'``: a single brick).

    Raises:
        nrc.errors.ConfigError: ``brick`` or ``free_flight`` is invalid (the message names the key).
    """
    if brick == "auto":
        brick = MajorantGrid.auto_brick(grid)
    elif isinstance(brick, bool) or not isinstance(brick, int) or brick < 1:
        raise ConfigError(f"renderer.brick must be 'auto' or an integer >= 1, got {brick!r}")
    if free_flight not in ("brick", "global"):
        raise ConfigError(f"renderer.free_flight must be 'brick' or 'global', got {free_flight!r}")
    majorants = MajorantGrid(grid, brick)
    return majorants, (majorants if free_flight == "brick" else MajorantGrid(grid, 0))


def roulette_threshold(transmittance: Any) -> float:
    """The ratio-tracking roulette threshold of the estimator (0 = off)."""
    return float(transmittance.params.get("roulette_threshold", 0.1))


@dataclass
class Core:
    """A renderer's transport core: the step's structure, its scene inputs and the chosen machine."""

    step: Transport  # the compiled structure
    eager_step: Transport  # the eager one (the same code; shadow rays queued for the estimator)
    inputs: SceneInputs
    majorants: MajorantGrid  # the shadow rays' brick majorants (the queued estimators use them)
    transmittance: Any
    device: torch.device
    backend: str
    steps_per_call: int
    compile_min_samples: int
    grid: Any = None
    bricks: Any = None
    scalars: tuple = ()  # (albedo, g, max_scatter, roulette threshold, throughput roulette) for P
    graphs: bool = False  # renderer.cuda_graphs: the machine's calls through CUDA graphs (graphs.py)
    last_startup_s: float = 0.0  # compile or cache-load seconds spent by the last choose()
    point_lights: tuple = ()  # sampled equi-angularly along segments (left out of the step's light table)
    _equiangular: Any = None  # their EquiangularSampler, built by the first equiangular_queue()
    # auto with the step in the persistent cache: compile (a ~4 s load) from this fraction of compile_min_samples
    # on. Measured break-evens (2 cores): pt saves ~4.4 us a camera sample (170k -> 650k samples/s), so a 4.5 s
    # warm start pays from ~1 M samples = 1/4 of its 4 M; an nrc path saves ~15 us (frame 0.92 -> 0.46 s for
    # 30,784 paths), so from ~0.3 M paths x frames = 1/12 of its 4 M.
    warm_fraction: float = 0.25

    def inputs_for(self, lights: LightSampler, **frame: Any) -> SceneInputs:
        """The scene inputs with other lights of the same structure (an animated sun) and the vertex program's
        numbers of this frame (``frame``, e.g. ``renderer.debias``'s probability): only ``P`` changes."""
        albedo, g, max_scatter, thr, rr = self.scalars
        P = self.step.params(self.grid, self.bricks, lights.table, albedo, g, max_scatter, thr, rr, **frame)
        return SceneInputs(P, self.inputs.density, self.inputs.majorant)

    def unsupported_reason(self) -> str | None:
        """Why this structure cannot be compiled (``None``: it can)."""
        if self.step.sampler is not None:
            return "lat-long environment maps have no compiled light sampler (directional, point, uniform sky only)"
        return None

    def choose(self, samples: int) -> tuple[Machine, str, str | None]:
        """``(machine, backend, reason)`` for a render of ``samples`` camera samples (see the module docstring)."""
        self.last_startup_s = 0.0
        if self.backend == "eager":
            return machine_for(self.eager_step, self.steps_per_call, False, self.device, self.graphs), "eager", None
        reason = self.unsupported_reason()
        if reason is None and self.backend == "auto" and not compiled_machine_ready(self.step, self.steps_per_call,
                                                                                  self.device):
            if packages_cached(self.step, self.steps_per_call, self.device):
                pass  # an AOT package loads in milliseconds: always worth it
            elif is_cached(self.step, self.device, self.steps_per_call):  # torch.compile's kernels (CUDA)
                warm_min = int(self.compile_min_samples * self.warm_fraction)
                if samples < warm_min:
                    reason = (f"{samples} samples < {warm_min} (renderer.compile_min_samples x {self.warm_fraction:.3g}):"
                              " even loading the cached compiled step (~4 s) would outweigh the speed-up")
            elif samples < self.compile_min_samples:
                reason = (f"{samples} camera samples < renderer.compile_min_samples={self.compile_min_samples} "
                          "and no compiled step in the cache (a cold compile would outweigh the speed-up)")
        if reason is None:
            machine = machine_for(self.step, self.steps_per_call, True, self.device, self.graphs)
            try:
                self.last_startup_s = machine.warm_up(self.inputs, 1 << 16)
                return machine, "compiled", None
            except Exception as exc:  # no C++ compiler, unsupported op, ...: the eager step still works
                reason = f"torch.compile failed: {type(exc).__name__}: {failure_line(exc)}"
        if self.backend == "compiled":
            log.warning("renderer.backend=compiled: falling back to eager: %s", reason)
        return machine_for(self.eager_step, self.steps_per_call, False, self.device, self.graphs), "eager", reason

    def equiangular_queue(self, batch: int, gen: torch.Generator) -> EquiangularQueue | None:
        """The queue for the point lights' equi-angular estimate (``None``: no point light is sampled that way);
        its estimator draws from ``gen``."""
        if not self.point_lights:
            return None
        albedo, g, max_scatter = self.scalars[:3]
        if self._equiangular is None:  # once per core: the phase table and the light choice serve every frame
            self._equiangular = EquiangularSampler(self.point_lights, self.grid, self.majorants, albedo, g,
                                                   self.transmittance)
        return EquiangularQueue(self._equiangular, int(max_scatter), batch, gen)

    def shadow_queue(self, machine: Machine, batch: int, gen: torch.Generator) -> ShadowQueue | None:
        """The queue for shadow rays that the machine's step does not trace itself (``None``: it does); its
        estimator draws from ``gen``."""
        if machine.step.inline_shadow:
            return None
        return ShadowQueue(self.transmittance, self.grid, self.majorants, batch, gen)


def build_core(scene: Any, transmittance: Any, settings: Any, program: VertexProgram | None = None,
               uniforms: Uniforms = counter_uniforms) -> Core:
    """The core for a scene and a renderer's settings, passed whole (its ``brick``, ``free_flight``, ``backend``,
    ``steps_per_call``, ``compile_min_samples``, ``cuda_graphs``, ``roulette``, ``light_sampling`` and ``inline_shadows``:
    ``False`` queues every shadow ray for the estimator), with the renderer's vertex program (default: ``pt``'s;
    :mod:`nrc.render.wavefront.program`). Point lights sampled equi-angularly are left out of the step's lights.
    """
    st = settings
    if st.backend not in BACKENDS:
        raise ConfigError(f"renderer.backend must be one of {', '.join(BACKENDS)}, got {st.backend!r}")
    for key, low in (("steps_per_call", 1), ("compile_min_samples", 0)):
        value = getattr(st, key)
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"renderer.{key} must be an integer >= {low}, got {value!r}")
    if st.cuda_graphs and scene.grid.device.type != "cuda":
        raise ConfigError(f"renderer.cuda_graphs=true needs device=cuda (the scene is on {scene.grid.device.type})")
    program = program if program is not None else VertexProgram()
    grid, lights = scene.grid, st.light_sampling.sampler(scene)
    albedo, g, max_scatter, rr = scene.albedo, scene.g, scene.integrator.max_scatter, st.roulette
    majorants, tracking = wavefront_majorants(grid, st.brick, st.free_flight)
    bricks = BrickTables(tracking, majorants)
    thr = roulette_threshold(transmittance)
    # Compiled pt: ratio-tracking shadow rays inside the step (one step a call for every slot). Eager, and
    # compiled nrc: shadow rays queued for the estimator, whose batched loop runs wide; inside the step a path's
    # shadow steps lengthen the chain of calls a frame waits for, which dominates NRC's short frames
    # (160x90, 1 spp: trace 0.33 s inline, 0.25 s queued; pt 128x72 x 64 spp: 0.99 s inline, 1.9 s queued).
    inline = transmittance.name == "ratio" and st.inline_shadows
    step = Transport(program, lights, bricks.n_tables, StepOptions(inline, thr > 0, rr is not None), uniforms)
    eager_step = Transport(program, lights, bricks.n_tables, StepOptions(False, thr > 0, rr is not None),
                           uniforms) if inline else step
    P = step.params(grid, bricks, step.lights, albedo, g, max_scatter, thr, rr)
    inputs = SceneInputs.build(P, grid.density, bricks.flat)
    return Core(step, eager_step, inputs, majorants, transmittance, grid.device, st.backend, st.steps_per_call,
                st.compile_min_samples, grid, bricks, (albedo, g, max_scatter, thr, rr), graphs=st.cuda_graphs,
                point_lights=tuple(st.light_sampling.equiangular_points(scene)))


def camera_rays(camera: Any, grid: DensityGrid, pix: Tensor, jitter: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(o, d, t0, t1)``: the camera rays through pixels ``pix`` ``(N,)`` at sub-pixel ``jitter`` ``(N, 2)`` and
    their span in the medium's box (``t0 >= t1`` where a ray misses it). The one place camera rays are made."""
    o, d = camera.generate_rays(pix, jitter)
    t0, t1 = grid.box.intersect(o, d)
    return o, d, t0, t1


def camera_paths(layout: Layout, camera: Any, grid: DensityGrid, pix: Tensor, jitter: Tensor,
                 key: Tensor) -> tuple[Tensor, Tensor]:
    """Packed state of new camera paths through pixels ``pix`` ``(N,)`` at sub-pixel ``jitter`` ``(N, 2)`` with
    RNG keys ``key``: origin at the camera, clipped to the box, throughput 1, accumulating into row ``pix``."""
    o, d, t0, t1 = camera_rays(camera, grid, pix, jitter)
    F, I = layout.zeros(len(pix), pix.device)
    F[layout.f("o")], F[layout.f("d")], F[layout.f("t")], F[layout.f("tmax")] = o.T, d.T, t0, t1
    F[layout.f("beta")] = 1.0
    I[layout.i("dest")], I[layout.i("key")], I[layout.i("flight")], I[layout.i("occupied")] = pix, key, FLIGHT, 1
    return F, I
