"""``renderer=pt``: the reference volumetric path tracer (batched wavefront, unbiased).

Estimator (per camera sample; SCENE.md conventions):

* Free flights by delta tracking against the brick majorants (a DDA over the majorant grid) or one global
  majorant (``renderer.free_flight``); at a real collision the path scatters (throughput x albedo), up to
  ``integrator.max_scatter`` real scattering events.
* Next-event estimation at every real scattering vertex: one light chosen uniformly among the scene's
  lights, its transmittance by the configured ``transmittance`` estimator. Environment light is also
  gathered by phase-sampled directions that escape the box, combined with NEE by the power heuristic
  (camera rays that escape see the environment with weight 1).
* Optional Russian roulette on the throughput (off by default).

Backends (``renderer.backend``): ``eager`` is the implementation below; ``compiled``
(:mod:`nrc.render.pt_compiled`) runs the same estimator as a ``torch.compile``'d per-slot state machine;
``auto`` picks ``compiled`` for renders of at least ``renderer.compile_min_samples`` camera samples when the
configuration is supported and ``torch.compile`` works, else ``eager``. Every fallback is recorded in the
metrics (``backend``, ``backend_reason``).

Execution (eager): a fixed working set of ``renderer.slots`` paths advances one delta-tracking step per
iteration; finished paths are replaced from the queue of camera samples, so every slot does useful work
until the queue runs dry. Scattering vertices push their next-event requests into a queue that is
traced in batches of ``renderer.shadow_batch`` rays by the transmittance estimator. Peak memory is
bounded by the working set and the shadow batch, independent of image size and spp:
about ``slots x 25 + shadow_batch x (40 + estimator state)`` floats (a few tens of MB at the defaults),
plus the ``(H x W x 3)`` float32 accumulation image.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import torch
from omegaconf import DictConfig
from torch import Tensor
from tqdm import tqdm

from nrc.errors import ConfigError
from nrc.render.result import RenderResult
from nrc.render.wavefront import refill_or_compact, wavefront_majorants
from nrc.scene import Scene
from nrc.transport.light_sampling import LightSampler
from nrc.transport.phase import hg_pdf, hg_sample
from nrc.transport.free_flight import delta_tracking_step
from nrc.transport.transmittance import make_transmittance

log = logging.getLogger(__name__)

BACKENDS = ("auto", "eager", "compiled")


def power_heuristic(a: Tensor, b: Tensor) -> Tensor:
    """``a^2 / (a^2 + b^2)``, 1 where both are zero."""
    a2, b2 = a * a, b * b
    den = a2 + b2
    return torch.where(den > 0, a2 / den.clamp(min=1e-30), torch.ones_like(den))


class PathTracer:
    """The wavefront path tracer (see module docstring).

    Args:
        scene: the validated scene.
        cfg: the app config (uses ``renderer``, ``transmittance``, ``scene.integrator``).
    """

    name = "pt"

    def __init__(self, scene: Scene, cfg: DictConfig) -> None:
        r = cfg.renderer
        self.scene = scene
        self.device = scene.device
        self.slots = int(r.get("slots", 1 << 16))
        self.shadow_batch = int(r.get("shadow_batch", 1 << 17))
        if self.slots < 1 or self.shadow_batch < 1:
            raise ConfigError("renderer.slots and renderer.shadow_batch must be >= 1")
        rr = r.get("russian_roulette") or {}
        self.rr_enabled = bool(rr.get("enabled", False))
        self.rr_start = int(rr.get("start", 8))
        self.free_flight = r.get("free_flight", "brick")
        self.majorants, self.tracking_majorants = wavefront_majorants(scene.grid, r.get("brick", "auto"),
                                                                      self.free_flight)
        self.transmittance = make_transmittance(cfg.get("transmittance"))
        self.lights = LightSampler(scene.lights, self.device)
        self.spp = scene.integrator.spp
        self.max_scatter = scene.integrator.max_scatter
        self.backend = r.get("backend", "eager")
        if self.backend not in BACKENDS:
            raise ConfigError(f"renderer.backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        self.steps_per_call = r.get("steps_per_call", 1)
        self.compile_min_samples = r.get("compile_min_samples", 0)
        for key, value, low in (("steps_per_call", self.steps_per_call, 1),
                                ("compile_min_samples", self.compile_min_samples, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"renderer.{key} must be an integer >= {low}, got {value!r}")
        self._machine: Any = None  # the compiled state machine, built on first use

    # ------------------------------------------------------------------ backend choice
    def _choose_backend(self) -> tuple[str, str | None]:
        """``(backend, reason)``: the backend to run and, when it is not the requested one (or ``auto`` chose
        eager), why."""
        from nrc.render import pt_compiled

        if self.backend == "eager":
            return "eager", None
        reason = pt_compiled.unsupported_reason(self)
        if reason is None and self.backend == "auto":
            total = self.scene.camera.num_pixels * self.spp
            if total < self.compile_min_samples:
                reason = (f"{total} camera samples < renderer.compile_min_samples={self.compile_min_samples} "
                          "(start-up would outweigh the speed-up)")
        if reason is None:
            try:
                if self._machine is None:
                    self._machine = pt_compiled.compiled_machine(self)
                self._machine.warm_up()
            except Exception as exc:  # no C++ compiler, unsupported op, ...: the eager tracer still works
                self._machine = None
                first = str(exc).splitlines()[0][:200] if str(exc) else ""
                reason = f"torch.compile failed: {type(exc).__name__}: {first}"
        if reason is not None:
            if self.backend == "compiled":
                log.warning("renderer.backend=compiled: falling back to eager: %s", reason)
            return "eager", reason
        return "compiled", None

    # ------------------------------------------------------------------ camera samples
    def _camera_paths(self, sample_ids: Tensor, gen: torch.Generator) -> dict[str, Tensor]:
        """New paths for camera sample ids (``pixel = id // spp``) starting at the box entry."""
        cam, grid = self.scene.camera, self.scene.grid
        pix = torch.div(sample_ids, self.spp, rounding_mode="floor")
        jitter = torch.rand(len(pix), 2, generator=gen, device=self.device)
        o, d = cam.generate_rays(pix, jitter)
        t0, t1 = grid.box.intersect(o, d)
        n = len(pix)
        return {
            "pix": pix, "o": o.contiguous(), "d": d, "t": t0, "t_max": t1,
            "beta": torch.ones(n, 3, device=self.device),
            "n": torch.zeros(n, dtype=torch.long, device=self.device),
            "pdf": torch.zeros(n, device=self.device),  # phase pdf of d; 0 marks a camera ray
        }

    # ------------------------------------------------------------------ next-event estimation
    def _flush_shadows(
        self,
        shadow_q: list[dict[str, Tensor]],
        image: Tensor,
        gen: torch.Generator,
        timers: dict[str, float],
        counts: dict[str, int],
    ) -> None:
        """Trace every queued next-event request (emptying the queue), timed and counted."""
        if not shadow_q:
            return
        t_sh = time.perf_counter()
        q = {k: torch.cat([b[k] for b in shadow_q]) for k in shadow_q[0]}
        shadow_q.clear()
        counts["shadow_rays"] += self._shade_shadow(q, image, gen)
        timers["shadow"] += time.perf_counter() - t_sh

    def _shade_shadow(self, q: dict[str, Tensor], image: Tensor, gen: torch.Generator) -> int:
        """Trace a batch of next-event requests and add their contributions; returns the ray count."""
        grid = self.scene.grid
        x, d_in = q["x"], q["d"]
        ls = self.lights.sample(x, torch.rand(len(x), 4, generator=gen, device=self.device))
        _, t_exit = grid.box.intersect(x, ls.wi)
        t1 = torch.minimum(t_exit, ls.distance)
        T = self.transmittance(grid, self.majorants, x, ls.wi, torch.zeros_like(t1), t1, gen)
        cos = (d_in * ls.wi).sum(-1)
        phase = hg_pdf(self.scene.g, cos)
        w = torch.where(ls.is_env, power_heuristic(ls.light_pdf, phase), torch.ones_like(phase))
        contrib = q["beta"] * ls.weight * (phase * T * w)[:, None]
        image.index_add_(0, q["pix"], contrib)
        return len(x)

    # ------------------------------------------------------------------ scattering
    def _scatter(
        self,
        s: dict[str, Tensor],
        trav: Any,
        idx: Tensor,
        x: Tensor,
        u_rr: Tensor,
        finished: Tensor,
        shadow_q: list[dict[str, Tensor]],
        gen: torch.Generator,
    ) -> None:
        """Real scattering at ``x`` for slots ``idx``: queue NEE, roulette, sample the phase function."""
        scene = self.scene
        n_new = s["n"][idx] + 1
        beta = s["beta"][idx] * scene.albedo
        if self.lights.n_lights:
            shadow_q.append({"x": x, "d": s["d"][idx], "beta": beta, "pix": s["pix"][idx]})
        # After the last vertex the path only continues if the sky can be reached by phase sampling (MIS).
        stop = beta.amax(-1) <= 0
        if not self.lights.has_env:
            stop = stop | (n_new >= self.max_scatter)
        if self.rr_enabled:
            q = beta.amax(-1).clamp(0.05, 1.0)
            in_rr = n_new >= self.rr_start
            stop = stop | (in_rr & (u_rr >= q))
            beta = torch.where(in_rr[:, None], beta / q[:, None], beta)
        d_new, pdf_new = hg_sample(scene.g, s["d"][idx], torch.rand(len(idx), 2, generator=gen, device=self.device))
        _, t_far = scene.grid.box.intersect(x, d_new)
        zero = torch.zeros_like(t_far)
        s["o"][idx] = x
        s["d"][idx] = d_new
        s["t"][idx] = zero
        s["t_max"][idx] = t_far
        s["beta"][idx] = beta
        s["n"][idx] = n_new
        s["pdf"][idx] = pdf_new
        trav.restart(idx, x, d_new, zero, t_far)
        finished[idx[stop]] = True

    # ------------------------------------------------------------------ main loop
    def render(self, progress: bool = False) -> RenderResult:
        """Render the scene with the configured backend; ``metrics`` name the backend, the start-up (compile)
        time apart from ``time_render_s``, and the reason for any fallback to eager."""
        backend, reason = self._choose_backend()
        if backend == "compiled":
            from nrc.render.pt_compiled import render_state_machine

            result = render_state_machine(self, self._machine, progress)
        else:
            result = self._render_eager(progress)
        result.metrics.update({"backend_requested": self.backend, "backend_reason": reason})
        return result

    def _render_eager(self, progress: bool) -> RenderResult:
        scene, dev = self.scene, self.device
        cam = scene.camera
        total = cam.num_pixels * self.spp
        gen = torch.Generator(device=dev).manual_seed(scene.integrator.seed)
        image = torch.zeros(cam.num_pixels, 3, device=dev)
        timers = {"free_flight": 0.0, "shadow": 0.0, "refill": 0.0}
        counts = {"tracking_steps": 0, "shadow_rays": 0, "iterations": 0, "empty_bricks_skipped": 0}
        has_env, n_lights = self.lights.has_env, self.lights.n_lights

        start = time.perf_counter()
        next_id = min(self.slots, total)
        s = self._camera_paths(torch.arange(next_id, device=dev), gen)
        trav = self.tracking_majorants.traverse(s["o"], s["d"], s["t"], s["t_max"])
        shadow_q: list[dict[str, Tensor]] = []
        queued = 0
        bar = tqdm(total=total, unit="sample", unit_scale=True, disable=not progress, desc="pt", leave=False,
                   mininterval=1.0)
        while len(s["pix"]) > 0:
            t_ff = time.perf_counter()
            counts["iterations"] += 1
            n_active = len(s["pix"])
            counts["tracking_steps"] += n_active
            u = torch.rand(n_active, 3, generator=gen, device=dev)
            # Runs of empty bricks are skipped without tracking steps (when enough rays sit in them);
            # then one delta-tracking step per slot against its brick's majorant: a tentative collision
            # inside the brick or a move to the brick's exit (memoryless restart there).
            skipped = trav.skip_empty(min_rays=n_active // 8)
            if skipped:  # rays moved past empty bricks resume tracking at their new brick's entry
                counts["empty_bricks_skipped"] += skipped
                s["t"] = torch.maximum(s["t"], trav.t)
            step = delta_tracking_step(scene.grid, trav, self.majorants.global_majorant, s["o"], s["d"], s["t"], u)
            x, real, escaped = step.x, step.real, step.escaped
            s["t"] = step.t
            finished = escaped.clone()

            # Escaping paths: environment radiance, MIS-weighted against NEE unless it is a camera ray.
            if has_env and bool(escaped.any()):
                e = escaped.nonzero().squeeze(1)
                d_e, pdf_e = s["d"][e], s["pdf"][e]
                le = self.lights.env_radiance(d_e)
                w = torch.where(pdf_e > 0, power_heuristic(pdf_e, self.lights.env_pdf(d_e)), torch.ones_like(pdf_e))
                image.index_add_(0, s["pix"][e], s["beta"][e] * le * w[:, None])

            if bool(real.any()):
                r = real.nonzero().squeeze(1)
                at_limit = s["n"][r] >= self.max_scatter  # the continuation of the last vertex collided
                scatter = r[~at_limit]
                finished[r[at_limit]] = True
                if len(scatter):
                    self._scatter(s, trav, scatter, x[scatter], u[scatter, 2], finished, shadow_q, gen)
                    queued += len(scatter) if n_lights else 0
            timers["free_flight"] += time.perf_counter() - t_ff

            if queued >= self.shadow_batch:
                self._flush_shadows(shadow_q, image, gen, timers, counts)
                queued = 0

            # Replace finished paths with new camera samples; compact once the queue is empty.
            t_rf = time.perf_counter()
            done = finished.nonzero().squeeze(1)
            if len(done):
                bar.update(len(done))
                s, next_id = refill_or_compact(s, trav, done, next_id, total, lambda ids: self._camera_paths(ids, gen))
            timers["refill"] += time.perf_counter() - t_rf
        self._flush_shadows(shadow_q, image, gen, timers, counts)
        bar.close()
        elapsed = time.perf_counter() - start
        img = (image / self.spp).reshape(cam.height, cam.width, 3)
        if not bool(torch.isfinite(img).all()):
            raise RuntimeError("path tracer produced non-finite pixels")
        metrics: dict[str, Any] = {
            "renderer": self.name,
            "backend": "eager",
            "free_flight": self.free_flight,
            "brick": self.majorants.brick,
            "transmittance": self.transmittance.name,
            "spp": self.spp,
            "samples": total,
            "time_render_s": elapsed,
            "samples_per_second": total / elapsed if elapsed > 0 else math.inf,
            **{f"time_{k}_s": v for k, v in timers.items()},
            **counts,
        }
        return RenderResult(image=img.cpu().numpy(), metrics=metrics)
