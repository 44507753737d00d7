"""The reuse pass (:class:`ReservoirReuse`; ``renderer.reuse.domain=light``, the base of the distance domain).

The render paths' reuse vertex ``R`` (the first real scattering vertex; the second with deferred reuse,
``|g| >= defer_g``) does no next-event estimate in the transport step: the driver records it
(:class:`~nrc.render.reuse.reservoirs.VertexRecord`) and after the wavefront this pass estimates its direct light:

1. **Initial reservoir**: the vertex's own RIS over ``M`` candidates of the source distribution
   (``renderer.light_selection``; ``M`` = ``renderer.ris.candidates`` for ``ris``, else 1), weighted
   ``p_hat / p_src``; it keeps ``y`` and the unbiased contribution weight ``W = sum w / (M p_hat(y))``.
2. **Temporal** (``spatiotemporal``): the previous frame's final reservoir of the pixel the vertex projects to,
   its confidence ``M`` clamped to ``history x M_candidates``.
3. **Spatial**: ``neighbors`` reservoirs of pixels in a ring of ``1 .. radius`` pixels (the same sample index).
4. **Shading**: the kept sample's shadow ray traced from the receiving vertex with the configured transmittance
   estimator: ``beta x f(y) x mis(y) x T x W``.

A light sample is ``y = (light index, direction)`` (:meth:`~nrc.transport.light_sampling.LightSampler.evaluate`);
its source pdf is the same at every vertex, so it moves between vertices without a Jacobian. The target is
``p_hat_i(y) = luminance(unshadowed light at x_i) x HG(d_i . wi) x mis_i(y)`` (times a march's transmittance with
``target=coarse`` or ``fine``). Steps 2 and 3 are generalized RIS with the ``reuse.mis`` weights (``balance`` or
``pairwise``). The derivation, why it is unbiased, and the measurements: ``docs/path_tracer.md``, "Reservoir reuse".

Memory: ``~30`` floats a sample slot (``width x height x spp``) for the record, the reservoirs and the history.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from nrc.render.reuse.extinction import CoarseTransmittance
from nrc.render.reuse.reservoirs import Reservoirs, VertexRecord, finish_ris, gather
from nrc.transport.light_sampling import LightSampler, power_heuristic
from nrc.transport.lights import luminance3
from nrc.transport.phase import hg_pdf
from nrc.transport.ris import ris_choice

if TYPE_CHECKING:
    from nrc.render.reuse.settings import ReuseSettings


class ReservoirReuse:
    """The reuse pass of one renderer (module docstring); keeps the previous frame's reservoirs.

    Args:
        settings: ``renderer.reuse``.
        g: the medium's HG asymmetry.
        spp: sample slots per pixel.
        grid: the density grid (the box for the targets' rays; the ``coarse`` target's density).
    """

    RESERVOIRS: type = Reservoirs
    TARGET_STEPS = 16  # march steps of the coarse / fine target's transmittance towards the light

    def __init__(self, settings: ReuseSettings, g: float, spp: int, grid: Any) -> None:
        self.settings, self.g, self.spp, self.grid = settings, float(g), int(spp), grid
        self.coarse = (CoarseTransmittance(grid, cells=0 if settings.target == "fine" else 32, steps=self.TARGET_STEPS)
                       if settings.target != "unshadowed" else None)
        self.prev: Reservoirs | None = None
        self.prev_camera: Any = None

    # ------------------------------------------------------------------ targets
    def target(self, lights: LightSampler, light: Tensor, omega: Tensor, x: Tensor, d: Tensor,
               mis: Tensor) -> Tensor:
        """``p_hat`` ``(N,)`` of samples ``(light, omega)`` at vertices ``(x, d, mis)``."""
        p, _ = self._target(lights, light, omega, x, d, mis)
        return p

    def _target(self, lights: LightSampler, light: Tensor, omega: Tensor, x: Tensor, d: Tensor,
                mis: Tensor) -> tuple[Tensor, Tensor]:
        """``(p_hat, p_hat / luminance(contribution))``: the target and its factor besides the light (phase x
        MIS x the coarse transmittance)."""
        wi, dist, c, p_src = lights.evaluate(light, omega, x)
        phase = hg_pdf(self.g, (d * wi).sum(-1))
        factor = phase * self._mis(lights, light, p_src, phase, mis)
        if self.coarse is not None:
            factor = factor * self.coarse(x, wi, torch.minimum(self.grid.box.intersect(x, wi)[1], dist))
        return luminance3(c.unbind(1)) * factor, factor

    @staticmethod
    def _mis(lights: LightSampler, light: Tensor, p_src: Tensor, phase: Tensor, mis: Tensor) -> Tensor | float:
        """The light-sampling MIS weight against phase sampling of the environment (1 for the delta lights and
        where the path does not go on): part of the integrand, so part of the target too (without it the
        resampling would favour sky directions in the phase lobe, which phase sampling covers)."""
        if not lights.has_env:
            return 1.0
        env = (light >= lights.env_index) & mis
        return torch.where(env, power_heuristic(p_src, phase), torch.ones_like(phase))

    def initial(self, rec: VertexRecord, lights: LightSampler, gen: torch.Generator) -> Reservoirs:
        """Each recorded vertex's RIS over the sampler's candidates (module docstring, step 1)."""
        n, dev = rec.n, rec.x.device
        m = lights.candidates
        u = torch.rand(n, 4 * m + 1, generator=gen, device=dev)
        ws, ps, ks, om = [], [], [], []
        for j in range(m):
            ls = lights.sample(rec.x, u[:, 4 * j:4 * j + 4])
            p, factor = self._target(lights, ls.light, ls.wi, rec.x, rec.d, rec.mis)
            ws.append(luminance3(ls.weight.unbind(1)) * factor)  # p_hat / p_src, p_src the pdf it was drawn with
            ps.append(p)
            ks.append(ls.light)
            om.append(ls.wi)
        sel, W, M = finish_ris(ws, ps, u[:, 4 * m], rec.valid)
        return Reservoirs(gather(ks, sel), gather(om, sel), W, M, rec.x, rec.d, rec.mis, rec.valid)

    def combine(self, inputs: list[Reservoirs], lights: LightSampler, u: Tensor) -> tuple[Reservoirs, Tensor]:
        """Generalized RIS of ``inputs`` (``inputs[0]`` the receivers) with the MIS weights of ``reuse.mis``
        (module docstring); returns the receivers' new reservoirs and the index of the input each kept."""
        rx = inputs[0]
        Ms = [torch.where(r.valid & rx.valid, r.M, torch.zeros_like(r.M)) for r in inputs]
        p0 = [self.target_at(lights, ri, rx) for ri in inputs]  # p_hat_0(y_i)
        m = self._mis_weights(inputs, Ms, p0, lights)
        ws = [m[i] * p0[i] * ri.W for i, ri in enumerate(inputs)]
        sel, total = ris_choice(ws, u)
        ph = gather(p0, sel)
        ok = rx.valid & (total > 0) & (ph > 0)
        W = torch.where(ok, total / ph.clamp(min=1e-30), torch.zeros_like(total))
        return rx.resampled(inputs, sel, W, sum(Ms)), sel

    def target_at(self, lights: LightSampler, r: Reservoirs, at: Reservoirs) -> Tensor:
        """``p_hat`` ``(N,)`` at ``at``'s vertices of ``r``'s samples (row-wise)."""
        return self.target(lights, r.light, r.omega, at.x, at.d, at.mis)

    def candidates(self, lights: LightSampler) -> int:
        """The initial RIS's candidates (the unit of the temporal history clamp)."""
        return lights.candidates

    def _mis_weights(self, inputs: list[Reservoirs], Ms: list[Tensor], p0: list[Tensor],
                     lights: LightSampler) -> list[Tensor]:
        """``m_i(y_i)`` per input: the generalized balance heuristic over every input's target (``balance``) or
        the pairwise weights against the receiver (``pairwise``); both sum to one over the inputs for any ``y``
        the receiver can produce and vanish where input ``i``'s target does. With two inputs they coincide."""
        def tgt(r: Reservoirs, at: Reservoirs) -> Tensor:  # p_hat at ``at``'s vertices of r's samples
            return self.target_at(lights, r, at)

        def ratio(a: Tensor, b: Tensor) -> Tensor:
            return torch.where(b > 0, a / b.clamp(min=1e-30), torch.zeros_like(b))

        k = len(inputs)
        if self.settings.mis == "balance" or k == 2:
            ph = [[p0[i] if j == 0 else tgt(ri, inputs[j]) for j in range(k)] for i, ri in enumerate(inputs)]
            return [ratio(Ms[i] * ph[i][i], sum(Ms[j] * ph[i][j] for j in range(k))) for i in range(k)]
        # pairwise: receiver c = 0 against each neighbour i with the neighbours' confidence N = sum M_i:
        # m_i(y) = M_i p_i(y) / (N p_i(y) + M_c p_c(y)),  m_c(y) = sum_i (M_i / N) M_c p_c(y) / (N p_i(y) + M_c p_c(y))
        rx, mc = inputs[0], Ms[0]
        n_nb = sum(Ms[1:])
        at_nb = [tgt(rx, ri) for ri in inputs[1:]]  # p_hat_i(y_0)
        m0 = torch.zeros_like(mc)
        for i, pi in enumerate(at_nb, start=1):
            m0 = m0 + ratio(Ms[i], n_nb) * ratio(mc * p0[0], n_nb * pi + mc * p0[0])
        m0 = torch.where(n_nb > 0, m0, torch.ones_like(m0))
        out = [m0]
        for i, ri in enumerate(inputs[1:], start=1):
            own = tgt(ri, ri)  # p_hat_i(y_i)
            out.append(ratio(Ms[i] * own, n_nb * own + mc * p0[i]))
        return out

    # ------------------------------------------------------------------ reuse
    def temporal(self, cur: Reservoirs, lights: LightSampler, gen: torch.Generator) -> tuple[Reservoirs, Tensor, Tensor]:
        """Combine with the previous frame's reservoir of the pixel the vertex projects to (step 2); returns
        the new reservoirs, the mask of vertices that found a history and the kept input's index."""
        n, dev = len(cur.W), cur.W.device
        pix, inside = self.prev_camera.project(cur.anchor)
        slot = pix * self.spp + torch.arange(n, device=dev) % self.spp
        prev = self.prev.take(slot)
        prev.valid = prev.valid & inside & cur.valid
        prev.M = torch.minimum(prev.M, torch.full_like(prev.M, self.settings.history * self.candidates(lights)))
        out, sel = self.combine([cur, prev], lights, torch.rand(n, generator=gen, device=dev))
        return out, prev.valid, sel

    def neighbours(self, camera: Any, gen: torch.Generator, n: int, device: torch.device) -> list[tuple[Tensor, Tensor]]:
        """``neighbors`` (slot, inside) pairs per sample slot: pixels in the ring ``1 .. radius`` around it."""
        st, W, H = self.settings, camera.width, camera.height
        ids = torch.arange(n, device=device)
        pix, j = torch.div(ids, self.spp, rounding_mode="floor"), ids % self.spp
        col, row = pix % W, torch.div(pix, W, rounding_mode="floor")
        u = torch.rand(st.neighbors, 2, n, generator=gen, device=device)
        out = []
        for k in range(st.neighbors):
            r = torch.sqrt(1.0 + u[k, 0] * (st.radius ** 2 - 1.0))  # uniform in the ring's area
            phi = 2.0 * math.pi * u[k, 1]
            c = col + torch.round(r * torch.cos(phi)).long()
            rr = row + torch.round(r * torch.sin(phi)).long()
            inside = (c >= 0) & (c < W) & (rr >= 0) & (rr < H)
            slot = torch.where(inside, (rr * W + c) * self.spp + j, ids)
            out.append((slot, inside))
        return out

    def spatial(self, cur: Reservoirs, camera: Any, lights: LightSampler,
                gen: torch.Generator) -> tuple[Reservoirs, Tensor]:
        """Combine each reservoir with ``neighbors`` of the same frame (step 3)."""
        n, dev = len(cur.W), cur.W.device
        inputs = [cur]
        for slot, inside in self.neighbours(camera, gen, n, dev):
            r = cur.take(slot)
            r.valid = r.valid & inside
            inputs.append(r)
        return self.combine(inputs, lights, torch.rand(n, generator=gen, device=dev))

    def shade(self, res: Reservoirs, rec: VertexRecord, lights: LightSampler, transmittance: Any, grid: Any,
              majorants: Any, gen: torch.Generator, batch: int) -> Tensor:
        """``beta x f(y) x mis x T x W`` ``(N, 3)`` of each reservoir's sample at its own vertex (step 4)."""
        out = torch.zeros(rec.n, 3, device=rec.x.device)
        idx = (res.valid & (res.W > 0)).nonzero().squeeze(1)
        for a in range(0, len(idx), batch):
            i = idx[a:a + batch]
            x, light = rec.x[i], res.light[i]
            wi, dist, c, p_src = lights.evaluate(light, res.omega[i], x)
            phase = hg_pdf(self.g, (rec.d[i] * wi).sum(-1))
            w = phase * res.W[i] * self._mis(lights, light, p_src, phase, rec.mis[i])
            t1 = torch.minimum(grid.box.intersect(x, wi)[1], dist)
            T = transmittance(grid, majorants, x, wi, torch.zeros_like(t1), t1, gen)
            out[i] = rec.beta[i] * c * (w * T)[:, None]
        return out

    def frame(self, rec: VertexRecord | None, camera: Any, lights: LightSampler, transmittance: Any, grid: Any,
              majorants: Any, gen: torch.Generator, batch: int) -> tuple[Tensor, dict[str, Any]]:
        """The reuse pass of a frame: ``(contribution (N, 3) per sample slot, counters)``; with
        ``spatiotemporal`` the frame's final reservoirs become the next frame's history. ``rec``: the recorded
        vertices (``domain=light``; :class:`~nrc.render.reuse.distance_reuse.DistanceReuse` draws its own camera
        rays through ``camera`` and takes none)."""
        t0 = time.perf_counter()
        mode = self.settings.mode
        if lights.n_lights == 0:  # nothing to sample (every light equi-angular, or none)
            n = rec.n if rec is not None else camera.num_pixels * self.spp
            valid = int(rec.valid.sum()) if rec is not None else 0
            return torch.zeros(n, 3, device=grid.device), {"reuse_vertices": valid,
                                                           "time_reuse_s": time.perf_counter() - t0}
        cur = self.frame_initial(rec, camera, lights, gen)
        valid = cur.valid
        n_valid = max(int(valid.sum()), 1)
        stats: dict[str, Any] = {"reuse_vertices": int(valid.sum())}
        if mode == "spatiotemporal" and self.prev is not None and len(self.prev.W) == len(cur.W):
            cur, hist, sel = self.temporal(cur, lights, gen)
            stats["reuse_temporal_found"] = int(hist.sum()) / n_valid
            stats["reuse_temporal_accept"] = int((hist & (sel == 1)).sum()) / n_valid
        if self.settings.neighbors:
            cur, sel = self.spatial(cur, camera, lights, gen)
            stats["reuse_spatial_accept"] = int((valid & (sel > 0)).sum()) / n_valid
        stats["reuse_mean_m"] = float(cur.M[valid].mean()) if bool(valid.any()) else 0.0
        if mode == "spatiotemporal":
            self.prev, self.prev_camera = cur, camera
        out = self.shade(cur, rec, lights, transmittance, grid, majorants, gen, batch)
        stats["time_reuse_s"] = time.perf_counter() - t0
        return out, stats

    def frame_initial(self, rec: VertexRecord | None, camera: Any, lights: LightSampler,
                      gen: torch.Generator) -> Reservoirs:
        """The frame's initial reservoirs, one per sample slot (the light domain: :meth:`initial` at the
        recorded vertices; the distance domain: on the camera rays)."""
        return self.initial(rec, lights, gen)

    def state_dict(self) -> dict[str, Any] | None:
        """The history (``None`` without one) for a checkpoint; the caller restores ``prev_camera``."""
        return None if self.prev is None else self.prev.state_dict()

    def load_state_dict(self, state: dict[str, Any] | None, camera: Any, device: torch.device) -> None:
        self.prev = None if state is None else self.RESERVOIRS.from_state(state, device)
        self.prev_camera = camera if state is not None else None
