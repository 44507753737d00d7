"""One wavefront for the NRC renderer's render paths and self-training paths.

Render paths (``spp`` per pixel) and training paths (one per training pixel) are traced in the same
working set of ``slots`` paths, with the path tracer's sampling (:mod:`nrc.render.pt`): delta tracking
against the brick majorants, next-event estimation at every real scattering vertex (one light chosen
uniformly, transmittance by the configured estimator), phase sampling with MIS against the environment.

Cache termination (:mod:`nrc.render.termination`) at a real scattering vertex ``m``: the path stops
without next-event estimation and adds ``beta x cache(x_m, d_m)`` where ``beta`` is its throughput up to
``x_m`` (before ``x_m``'s albedo) and ``d_m`` the unit direction of travel arriving at ``x_m``. The cache
therefore stores the radiance scattered at ``x`` towards ``-d`` (albedo included): ``L_s(x, d) = albedo x
integral of phase(d, w) L_i(x, w) dw``. Paths that leave the medium never query the cache; pixels whose
camera ray never scatters only see the environment.

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

Contributions land in one accumulator ``acc`` of ``P + N_train x V + 1`` rows: rows ``[0, P)`` are image
pixels (sums over the ``spp`` samples), then ``V`` rows per training path, then one discard row for
training paths that have not scattered yet. Cache queries are returned (not evaluated) so the caller
can batch and filter them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from nrc.render.camera import Camera
from nrc.render.pt import power_heuristic
from nrc.render.sampler import RandomSource
from nrc.render.termination import Termination
from nrc.render.wavefront import refill_or_compact
from nrc.scene import Scene
from nrc.transport.light_sampling import LightSampler
from nrc.transport.phase import hg_pdf, hg_sample
from nrc.transport.free_flight import delta_tracking_step
from nrc.volume.majorant import MajorantGrid

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
    then training paths). ``rec_*`` are ``(N_train * V, ...)``: record position, direction and whether
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


class NRCPathTracer:
    """Traces the render and training paths of a frame (see the module docstring).

    Args:
        scene: the validated scene (medium, albedo, g, ``integrator.max_scatter``).
        majorants: brick majorants used by the shadow-ray estimator.
        tracking_majorants: majorants of the free flights (brick or a single global brick).
        transmittance: the shadow-ray estimator (``make_transmittance``).
        termination: the cache-termination rule.
        records_per_path: training records kept per training path (``V >= 1``).
        extra_vertices: vertices a training path goes past the render path's stop (``>= 0``).
        slots: paths in flight; shadow_batch: next-event rays traced per estimator call.
    """

    def __init__(self, scene: Scene, majorants: MajorantGrid, tracking_majorants: MajorantGrid, transmittance: Any,
                 termination: Termination, records_per_path: int, extra_vertices: int, slots: int,
                 shadow_batch: int) -> None:
        self.scene = scene
        self.device = scene.device
        self.majorants = majorants
        self.tracking_majorants = tracking_majorants
        self.transmittance = transmittance
        self.termination = termination
        self.V = records_per_path
        self.extra_vertices = extra_vertices
        self.slots = slots
        self.shadow_batch = shadow_batch

    # ------------------------------------------------------------------ new paths
    def _new_paths(self, ids: Tensor, ps: PathSet, rng: RandomSource, n_rows: int) -> dict[str, Tensor]:
        cam, dev = ps.camera, self.device
        n = len(ids)
        is_train = ids >= ps.n_render
        k = (ids - ps.n_render).clamp(min=0)
        jitter = rng.rand(n, 2)
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
        o, d = cam.generate_rays(pix, jitter)
        t0, t1 = self.scene.grid.box.intersect(o, d)
        zeros = torch.zeros(n, device=dev)
        return {
            "pid": ids, "dest": torch.where(is_train, n_rows - 1, pix), "o": o.contiguous(), "d": d, "t": t0,
            "t_max": t1, "beta": torch.ones(n, 3, device=dev), "n": torch.zeros_like(ids), "pdf": zeros,
            "extra": torch.where(is_train, self.extra_vertices, 0), "never": never,
            "n_term": torch.zeros_like(ids),
            "rec_base": torch.where(is_train, cam.num_pixels + k * self.V, -1),
            "spread": zeros.clone(), "a0": zeros.clone(), "x_prev": o.contiguous().clone(),
        }

    # ------------------------------------------------------------------ next-event estimation
    def _shade_shadows(self, q: dict[str, Tensor], acc: Tensor, lights: LightSampler, rng: RandomSource) -> None:
        grid = self.scene.grid
        x, d_in = q["x"], q["d"]
        ls = lights.sample(x, rng.rand(len(x), 4))
        _, t_exit = grid.box.intersect(x, ls.wi)
        t1 = torch.minimum(t_exit, ls.distance)
        T = self.transmittance(grid, self.majorants, x, ls.wi, torch.zeros_like(t1), t1, rng.generator)
        phase = hg_pdf(self.scene.g, (d_in * ls.wi).sum(-1))
        w = torch.where(ls.is_env, power_heuristic(ls.light_pdf, phase), torch.ones_like(phase))
        acc.index_add_(0, q["dest"], q["beta"] * ls.weight * (phase * T * w)[:, None])

    # ------------------------------------------------------------------ a real collision
    def _vertex(self, s: dict[str, Tensor], trav: Any, idx: Tensor, x: Tensor, u_term: Tensor, finished: Tensor,
                out: dict[str, list[Tensor]], rec: dict[str, Tensor], lights: LightSampler, rng: RandomSource,
                n_pixels: int) -> int:
        """Real scattering vertex at ``x`` for slots ``idx``; returns the number of next-event rays queued."""
        scene = self.scene
        n_new = s["n"][idx] + 1
        d_in = s["d"][idx]
        spread, a0 = self.termination.spread_update(n_new, x, s["x_prev"][idx], s["pdf"][idx], s["spread"][idx],
                                                     s["a0"][idx])
        fire = self.termination.fires(n_new, u_term, spread, a0)
        n_term = s["n_term"][idx]
        n_term = torch.where(fire & (n_term == 0) & ~s["never"][idx], n_new + s["extra"][idx], n_term)
        terminate = (n_term > 0) & (n_new >= n_term)

        t = terminate.nonzero().squeeze(1)
        if len(t):
            out["x"].append(x[t])
            out["d"].append(d_in[t])
            out["w"].append(s["beta"][idx[t]])
            out["dest"].append(s["dest"][idx[t]])
            out["pid"].append(s["pid"][idx[t]])
            finished[idx[t]] = True
        c = (~terminate).nonzero().squeeze(1)
        if not len(c):
            return 0
        i, x, d_in, n_new = idx[c], x[c], d_in[c], n_new[c]
        rec_base = s["rec_base"][i]
        is_train = rec_base >= 0
        recorded = is_train & (n_new <= self.V)
        beta = torch.where(recorded[:, None], torch.full_like(s["beta"][i], scene.albedo), s["beta"][i] * scene.albedo)
        dest = torch.where(is_train, rec_base + torch.clamp(n_new, max=self.V) - 1, s["dest"][i])
        r = recorded.nonzero().squeeze(1)
        if len(r):
            slot = dest[r] - n_pixels
            rec["x"][slot] = x[r]
            rec["d"][slot] = d_in[r]
            rec["valid"][slot] = True
        queued = 0
        if lights.n_lights:
            out["nee"].append({"x": x, "d": d_in, "beta": beta, "dest": dest})
            queued = len(c)
        stop = beta.amax(-1) <= 0
        if not lights.has_env:  # the last vertex only continues when phase sampling can reach the sky (MIS)
            stop = stop | (n_new >= scene.integrator.max_scatter)
        d_new, pdf_new = hg_sample(scene.g, d_in, rng.rand(len(c), 2))
        _, t_far = scene.grid.box.intersect(x, d_new)
        zero = torch.zeros_like(t_far)
        for name, value in (("o", x), ("d", d_new), ("t", zero), ("t_max", t_far), ("beta", beta), ("n", n_new),
                            ("pdf", pdf_new), ("dest", dest), ("n_term", n_term[c]), ("spread", spread[c]),
                            ("a0", a0[c]), ("x_prev", x)):
            s[name][i] = value
        trav.restart(i, x, d_new, zero, t_far)
        finished[i[stop]] = True
        return queued

    # ------------------------------------------------------------------ main loop
    def trace(self, ps: PathSet, lights: LightSampler, rng: RandomSource) -> FrameTrace:
        """Trace every path of ``ps``; NEE lands in ``acc``, cache terminations are returned as queries."""
        scene, dev, V = self.scene, self.device, self.V
        n_pixels = ps.camera.num_pixels
        total = ps.n_render + ps.n_train
        n_rows = n_pixels + ps.n_train * V + 1
        acc = torch.zeros(n_rows, 3, device=dev)
        rec = {"x": torch.zeros(ps.n_train * V, 3, device=dev), "d": torch.zeros(ps.n_train * V, 3, device=dev),
               "valid": torch.zeros(ps.n_train * V, dtype=torch.bool, device=dev)}
        scattered = torch.zeros(ps.n_train, dtype=torch.bool, device=dev)
        out: dict[str, list[Any]] = {"x": [], "d": [], "w": [], "dest": [], "pid": [], "nee": []}
        timers = {"free_flight": 0.0, "shadow": 0.0}
        counts = {"tracking_steps": 0, "shadow_rays": 0, "iterations": 0, "empty_bricks_skipped": 0}
        max_scatter = scene.integrator.max_scatter
        queued = 0

        def flush() -> None:
            nonlocal queued
            if out["nee"]:
                t_sh = time.perf_counter()
                q = {k: torch.cat([b[k] for b in out["nee"]]) for k in out["nee"][0]}
                out["nee"].clear()
                self._shade_shadows(q, acc, lights, rng)
                counts["shadow_rays"] += len(q["x"])
                timers["shadow"] += time.perf_counter() - t_sh
            queued = 0

        next_id = min(self.slots, total)
        s = self._new_paths(torch.arange(next_id, device=dev), ps, rng, n_rows)
        trav = self.tracking_majorants.traverse(s["o"], s["d"], s["t"], s["t_max"])
        while len(s["pid"]) > 0:
            t_ff = time.perf_counter()
            n_active = len(s["pid"])
            counts["tracking_steps"] += n_active
            counts["iterations"] += 1
            skipped = trav.skip_empty(min_rays=n_active // 8)
            if skipped:  # rays moved past empty bricks resume tracking at their new brick's entry
                counts["empty_bricks_skipped"] += skipped
                s["t"] = torch.maximum(s["t"], trav.t)
            u = rng.rand(n_active, 3)
            step = delta_tracking_step(scene.grid, trav, self.majorants.global_majorant, s["o"], s["d"], s["t"], u)
            x, real, escaped = step.x, step.real, step.escaped
            s["t"] = step.t
            finished = escaped.clone()

            if lights.has_env and bool(escaped.any()):
                e = escaped.nonzero().squeeze(1)
                d_e, pdf_e = s["d"][e], s["pdf"][e]
                w = torch.where(pdf_e > 0, power_heuristic(pdf_e, lights.env_pdf(d_e)), torch.ones_like(pdf_e))
                acc.index_add_(0, s["dest"][e], s["beta"][e] * lights.env_radiance(d_e) * w[:, None])

            if bool(real.any()):
                r = real.nonzero().squeeze(1)
                first = r[s["n"][r] == 0]
                train_first = s["pid"][first] >= ps.n_render
                scattered[s["pid"][first[train_first]] - ps.n_render] = True
                at_limit = s["n"][r] >= max_scatter  # the continuation of the last vertex collided
                finished[r[at_limit]] = True
                v = r[~at_limit]
                if len(v):
                    queued += self._vertex(s, trav, v, x[v], u[v, 2], finished, out, rec, lights, rng, n_pixels)
            timers["free_flight"] += time.perf_counter() - t_ff
            if queued >= self.shadow_batch:
                flush()

            done = finished.nonzero().squeeze(1)
            if len(done):
                s, next_id = refill_or_compact(s, trav, done, next_id, total,
                                               lambda ids: self._new_paths(ids, ps, rng, n_rows))
        flush()

        def cat(name: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
            return torch.cat(out[name]) if out[name] else torch.zeros(shape, dtype=dtype, device=dev)

        counts["cache_queries"] = sum(len(v) for v in out["pid"])
        return FrameTrace(
            acc=acc, n_pixels=n_pixels,
            query_x=cat("x", (0, 3), torch.float32), query_d=cat("d", (0, 3), torch.float32),
            query_w=cat("w", (0, 3), torch.float32), query_dest=cat("dest", (0,), torch.long),
            query_pid=cat("pid", (0,), torch.long), rec_x=rec["x"], rec_d=rec["d"], rec_valid=rec["valid"],
            scattered=scattered, counts=counts, timers=timers,
        )
