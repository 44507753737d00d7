"""One wavefront for the NRC renderer's render paths and self-training paths.

Render paths (``spp`` per pixel) and training paths (one per training pixel) are traced in the same
working set of ``slots`` paths by the path tracer's transport core (:mod:`nrc.render.wavefront`, the same
step code, eager or compiled: ``renderer.backend``): delta tracking against the brick majorants, next-event
estimation at every real scattering vertex (one light chosen by ``renderer.light_selection``, transmittance
by ratio tracking in the step or the configured estimator), phase sampling with MIS against the environment. The NRC part of the
step is its vertex: the termination rule, the training records and the cache query. With ``renderer.reuse`` the
render paths' first vertex is recorded instead of estimating its direct light, which the renderer's reuse pass
adds (:mod:`nrc.render.reuse`; a path that terminates there into the cache is recorded only with
``cache_target=indirect``, whose terminating vertices estimate their direct light).

Cache termination (:mod:`nrc.render.radiance_caching.termination`) at a real scattering vertex ``m``: the path stops
without next-event estimation and adds ``beta x cache(x_m, d_m)`` where ``beta`` is its throughput up to
``x_m`` (before ``x_m``'s albedo) and ``d_m`` the unit direction of travel arriving at ``x_m``. The cache
therefore stores the radiance scattered at ``x`` towards ``-d`` (albedo included): ``L_s(x, d) = albedo x
integral of phase(d, w) L_i(x, w) dw``. Paths that leave the medium never query the cache; pixels whose
camera ray never scatters only see the environment.

``cache_target=indirect`` (``renderer.cache_target``) moves the direct light out of the cache: the cache
stores ``L_s`` minus the single-scattered light of the lights (next-event estimation with MIS and the
environment reached by phase sampling, both at ``x``), and a terminating path adds its own next-event
estimate by light sampling alone (weight 1, no MIS: the path does not go on to find the environment by phase
sampling) besides ``beta x cache``. A record's target is then ``T_j - D_j`` with ``D_j`` its own direct light
(kept in separate rows of ``acc``). The cache no longer has to reproduce the phase function's peak towards a
sun (at g 0.95, a 3-degree lobe); next-event estimation does that exactly.

Training paths continue ``extra_vertices`` real vertices past the vertex where the rule would stop a
render path, then terminate into the cache (self-training); a fraction of them (``unbiased_fraction``,
drawn per path) never does and runs to ``max_scatter`` (unbiased suffixes). Vertex ``j = 1..V`` of a
training path (``V = records_per_path``) that is not its terminal vertex becomes a training record
``(x_j, d_j) -> T_j`` with ``T_j = L_s`` estimated by the rest of the path::

    T_j = acc_j + albedo x T_{j+1}

where ``acc_j`` sums, with the throughput *relative to vertex j* (``albedo`` at ``j``, times the albedo of
every later vertex beyond ``V``, which all add into ``acc_V``), the next-event estimate at ``j``, the
MIS-weighted environment reached by the direction sampled at ``j``, and the cache value at the terminal
vertex if it follows ``j``. Everything is float32.

With ``renderer.debias`` (:mod:`nrc.render.radiance_caching.debias`) a render path that would terminate goes on
with probability ``q`` as a path-traced suffix (throughput ``beta / q``) and its cache query gets the weight
``beta (1 - 1/q)``: the cache is a control variate and the image is unbiased.

Contributions land in one accumulator ``acc`` of ``P + N_train x V + 1`` rows: rows ``[0, P)`` are image
pixels (sums over the ``spp`` samples), then ``V`` rows per training path, then one discard row for
training paths that have not scattered yet; with ``cache_target=indirect`` then ``N_train x V`` rows of the
records' own direct light; with ``renderer.debias`` then one suffix row per render sample (zero unless the
sample was continued; the caller adds them to the pixels). Cache queries are returned (not evaluated) so the
caller can batch and filter them.
"""

from __future__ import annotations

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

    @property
    def n_render(self) -> int:
        return self.camera.num_pixels * self.spp

    @property
    def n_train(self) -> int:
        return int(self.train_xy.shape[0])


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
    direct: Tensor | None = None  # cache_target=indirect: (N_train * V, 3) each record's direct light
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

    def _core(self, uniforms):
        if uniforms not in self._cores:
            self._cores[uniforms] = build_core(self.scene, self.transmittance, self.settings, self.program, uniforms)
            self._cores[uniforms].warm_fraction = 1 / 12  # see Core.warm_fraction
        return self._cores[uniforms]

    # ------------------------------------------------------------------ new paths
    def _new_paths(self, ids: Tensor, ps: PathSet, rng: RandomSource, layout, discard: int) -> tuple[Tensor, Tensor]:
        """Packed new paths for ids; training paths accumulate into ``discard`` until their first vertex."""
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
        I[layout.i("rec")] = -1
        I[layout.i("dest")] = torch.where(is_train, discard, pix)
        I[layout.i("pid")] = ids
        I[layout.i("extra")] = torch.where(is_train, self.extra_vertices, 0)
        I[layout.i("never")] = never.long()
        I[layout.i("rec_base")] = torch.where(is_train, k * self.V, -1)
        return F, I

    # ------------------------------------------------------------------ main loop
    def trace(self, ps: PathSet, lights: LightSampler, rng: RandomSource, debias_q: float = 0.0) -> FrameTrace:
        """Trace every path of ``ps``; NEE lands in ``acc``, cache terminations are returned as queries
        (``debias_q``: the probability that a render path goes on past its cache termination, with
        ``renderer.debias``; in ``(0, 1]``)."""
        dev, V = self.device, self.V
        core = self._core(rng.counter_uniforms)
        n_pixels = ps.camera.num_pixels
        total = ps.n_render + ps.n_train
        discard = n_pixels + ps.n_train * V
        indirect = self.cache_target == "indirect"
        n_rows = discard + 1 + (ps.n_train * V if indirect else 0)
        suffix_base = n_rows if self.debias else None
        if self.debias:
            if not 0.0 < debias_q <= 1.0:
                raise ValueError(f"debias_q must be in (0, 1], got {debias_q}")
            n_rows += ps.n_render
        acc = torch.zeros(n_rows, 3, device=dev)
        machine, self.backend, self.backend_reason = core.choose(total * self.frames)
        rec = self.settings.reuse.record(ps.n_render, self.scene.g, self.scene.albedo, dev)
        hv = NRCCollector(n_pixels, ps.n_render, V, torch.zeros(ps.n_train * V, 3, device=dev),
                          torch.zeros(ps.n_train * V, 3, device=dev),
                          torch.zeros(ps.n_train * V, dtype=torch.bool, device=dev),
                          torch.zeros(ps.n_train, dtype=torch.bool, device=dev), discard + 1 if indirect else None,
                          debias_q=debias_q if self.debias else 0.0, suffix_base=suffix_base, watchers=(rec,))
        queues = Queues(core.shadow_queue(machine, self.shadow_batch, rng.generator),
                        core.equiangular_queue(self.shadow_batch, rng.generator))
        frame = {"debias_q": debias_q} if self.debias else {}
        wf = Wavefront(machine, core.inputs_for(lights, **frame), lights, self.slots, queues, hv)
        layout = machine.step.layout
        wf.run(total, lambda ids: self._new_paths(ids, ps, rng, layout, discard), acc)
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
        return FrameTrace(
            acc=acc, n_pixels=n_pixels,
            query_x=cat("x", (0, 3), torch.float32), query_d=cat("d", (0, 3), torch.float32),
            query_w=cat("w", (0, 3), torch.float32), query_dest=cat("dest", (0,), torch.long),
            query_pid=cat("pid", (0,), torch.long), rec_x=hv.rec_x, rec_d=hv.rec_d, rec_valid=hv.rec_valid,
            scattered=hv.scattered, counts=counts, timers=timers,
            direct=acc[discard + 1:discard + 1 + ps.n_train * V] if indirect else None, reuse=rec, **debias,
        )
