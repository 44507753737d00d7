"""Distance reuse (``renderer.reuse.domain=distance``; Lin, Wyman and Yuksel 2021): reservoirs of pairs ``(t, y)``,
a distance along the pixel's camera ray and a light sample, resampled as the light domain's
(:mod:`nrc.render.reuse.light_reuse`); the pass estimates each camera ray's single scattering of the sampled
lights. The estimator and its measurements: ``docs/path_tracer.md``, "Distance reuse".

Memory: ``~20 + 2 x distance_steps`` floats a sample slot (each ray's extinction table, in the reservoirs and the
history).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from nrc.render.reuse.extinction import ExtinctionTable
from nrc.render.reuse.light_reuse import ReservoirReuse
from nrc.render.reuse.reservoirs import finish_ris, gather
from nrc.render.wavefront.setup import camera_rays
from nrc.transport.light_sampling import LightSampler
from nrc.transport.lights import luminance3
from nrc.transport.phase import hg_pdf

if TYPE_CHECKING:
    from nrc.render.reuse.settings import ReuseSettings


@dataclass
class DistanceReservoirs(ExtinctionTable):
    """``domain=distance``: one reservoir per sample slot holding a pair ``(t, y)``: the distance ``t`` ``(N,)``
    along the slot's camera ray and the light sample ``(light, omega)``; ``W``, ``M`` as
    :class:`~nrc.render.reuse.reservoirs.Reservoirs`; the camera ray (``o``, ``d`` ``(N, 3)``; ``ta``, ``tb``
    ``(N,)`` its span in the box) and its extinction table (:class:`~nrc.render.reuse.extinction._Table`, ``cum``
    ``(N, S)``, ``S = distance_steps``: the distance source, the targets' transmittance and the camera segment's
    control); ``valid``: the ray crosses the box."""

    t: Tensor
    light: Tensor
    omega: Tensor
    W: Tensor
    M: Tensor
    SAMPLE = ("t", "light", "omega")

    @property
    def anchor(self) -> Tensor:
        """The kept sample's point: temporal reuse finds the previous frame's pixel through it."""
        return self.o + self.t[:, None] * self.d


class DistanceReuse(ReservoirReuse):
    """Reuse of ``(distance, light)`` pairs on the camera rays (``renderer.reuse.domain=distance``; Lin, Wyman
    and Yuksel 2021, with the generalized RIS of :mod:`nrc.render.reuse.light_reuse`).

    The pixel's single scattering of the sampled lights, ``I = int_ta^tb T(ta, t) sigma_s(x_t) int
    p(d, wi) L(x_t, wi) T(x_t -> y) dy dt`` along its camera ray ``x_t = o + t d``, is estimated by this pass
    alone; the render path's first vertex does no next-event estimate of those lights and its phase-sampled
    direction does not count the environment it reaches (:attr:`ReuseSettings.light_only`; the camera ray's
    escape and the rest of the path stay the path's). The direct light of the first vertex is thus resampled
    over where the vertex is, not only over which light: reuse spreads good distances across pixels, which the
    ``light`` domain cannot.

    - **Samples.** ``z = (t, y)``; a pair shifts to another pixel's camera ray at the same ``t`` (the measure
      ``dt x dy`` is the same on every ray: no Jacobian), the light sample as in the ``light`` domain.
    - **Source.** ``t`` from the extinction table ``sig`` along the ray (the grid read at the midpoints of
      ``distance_steps`` equal steps; pdf ``sig(t) exp(-tau(t)) / (1 - exp(-tau_total))``) mixed
      with a uniform share :attr:`UNIFORM` over ``[ta, tb]`` (positive wherever the medium can be), then one
      light sample at ``x_t`` from ``renderer.light_selection``; ``distance_candidates`` such pairs.
    - **Target.** ``p_hat(t, y) = sigma_s(x_t) exp(-tau(t)) luminance(L) HG`` (times the coarse
      transmittance towards the light with ``target=coarse``): the integrand without the two visibilities.
      No MIS against phase sampling (the light sampling covers the whole of ``I``).
    - **Shading.** ``sigma_s(x_t) T(ta, t) HG L T(x_t -> y) W``, added to the slot. Both transmittances are
      residual ratio tracking against an extinction table
      (:meth:`~nrc.render.reuse.extinction._Table.transmittance`; unbiased): the camera segment against the ray's
      own table (:attr:`CAMERA_POINTS` residual lookups), the shadow segment against a :attr:`LIGHT_STEPS`-step
      table marched for it (:attr:`LIGHT_POINTS`). Not the configured
      ``transmittance`` estimator: on the side-lit Disney cloud the table-controlled camera estimate has a tenth
      of ratio tracking's variance at a tenth of its time, and the shading's weight ``f / p_hat`` carries that
      variance straight into the pixel.

    Needs ``cache_target=indirect`` under ``nrc`` (with ``full`` a path terminating at its first vertex would
    count that vertex's direct light in the cache's answer too).
    """

    RESERVOIRS = DistanceReservoirs
    UNIFORM = 0.25
    CAMERA_POINTS = 8  # density lookups a camera segment's transmittance takes on average (table control)
    LIGHT_STEPS = 64  # the shadow segment's control table
    LIGHT_POINTS = 8  # and its residual lookups on average

    def __init__(self, settings: ReuseSettings, g: float, spp: int, grid: Any, albedo: float) -> None:
        super().__init__(settings, g, spp, grid)
        self.albedo = float(albedo)

    def candidates(self, lights: LightSampler) -> int:
        return self.settings.distance_candidates

    # ------------------------------------------------------------------ rays, distances, targets
    def rays(self, camera: Any, n: int, gen: torch.Generator) -> DistanceReservoirs:
        """Empty reservoirs on ``n`` jittered camera rays (slot ``pixel x spp + j``) with their coarse tables."""
        dev = self.grid.device
        ids = torch.arange(n, device=dev)
        pix = torch.div(ids, self.spp, rounding_mode="floor")
        o, d, ta, tb = camera_rays(camera, self.grid, pix, torch.rand(n, 2, generator=gen, device=dev))
        o, d = o.contiguous(), d.contiguous()
        ta = ta.clamp(min=0.0)
        valid = tb > ta
        tb = torch.where(valid, tb, ta)
        tab = ExtinctionTable.march(self.grid.sigma_t, o, d, ta, tb, self.settings.distance_steps)
        z = torch.zeros(n, device=dev)
        return DistanceReservoirs(o, d, ta, tb, tab.cum, valid, t=z, W=z.clone(), M=z.clone(),
                                  light=torch.zeros(n, dtype=torch.long, device=dev),
                                  omega=torch.zeros(n, 3, device=dev))

    def _mix(self, r: DistanceReservoirs) -> Tensor:
        """The exponential share of the distance source (none on a ray whose table depth is 0)."""
        return torch.where(r.total() > 1e-6, torch.full_like(r.ta, 1.0 - self.UNIFORM), torch.zeros_like(r.ta))

    def distance_pdf(self, r: DistanceReservoirs, t: Tensor) -> Tensor:
        """The source pdf ``(N,)`` of distances ``t`` on rays ``r`` (0 outside ``[ta, tb]``)."""
        tau, sig_k, inside = r.tau(t)
        a = self._mix(r)
        norm = (-torch.expm1(-r.total())).clamp(min=1e-30)
        p = a * sig_k * torch.exp(-tau) / norm + (1.0 - a) / (r.tb - r.ta).clamp(min=1e-30)
        return torch.where(inside, p, torch.zeros_like(p))

    def sample_distance(self, r: DistanceReservoirs, u0: Tensor, u1: Tensor) -> Tensor:
        """Distances ``(N,)`` on rays ``r`` from the source (``u0`` picks the part, ``u1`` inverts it)."""
        S = r.cum.shape[1]
        span = r.tb - r.ta
        h = span / S
        uniform = r.ta + u1 * span
        target = -torch.log1p(-u1 * (-torch.expm1(-r.total())))  # optical depth of the exponential part
        k = torch.searchsorted(r.cum.contiguous(), target[:, None].contiguous(), right=True)[:, 0].clamp(max=S - 1)
        rows = torch.arange(len(u0), device=u0.device)
        sig_k = r.step_sigma(rows, k, h)
        into = (target - (r.cum[rows, k] - sig_k * h)) / sig_k.clamp(min=1e-30)
        expo = r.ta + k.to(u1.dtype) * h + into.clamp(min=0.0).minimum(h)
        return torch.where(u0 < self._mix(r), expo, uniform).clamp(min=r.ta, max=r.tb)

    def _dtarget(self, lights: LightSampler, t: Tensor, light: Tensor, omega: Tensor,
                 at: DistanceReservoirs) -> tuple[Tensor, Tensor]:
        """``(p_hat, p_hat / luminance(L))`` of samples ``(t, light, omega)`` on ``at``'s rays."""
        tau, _, inside = at.tau(t)
        x = at.o + t[:, None] * at.d
        wi, dist, c, _ = lights.evaluate(light, omega, x)
        factor = self.albedo * self.grid.sigma_t(x) * torch.exp(-tau) * hg_pdf(self.g, (at.d * wi).sum(-1))
        if self.coarse is not None:
            factor = factor * self.coarse(x, wi, torch.minimum(self.grid.box.intersect(x, wi)[1], dist))
        factor = torch.where(inside, factor, torch.zeros_like(factor))
        return luminance3(c.unbind(1)) * factor, factor

    def target_at(self, lights: LightSampler, r: Any, at: Any) -> Tensor:
        return self._dtarget(lights, r.t, r.light, r.omega, at)[0]

    # ------------------------------------------------------------------ the pass
    def frame_initial(self, rec: Any, camera: Any, lights: LightSampler, gen: torch.Generator) -> DistanceReservoirs:
        return self.initial(camera, camera.num_pixels * self.spp, lights, gen)

    def initial(self, camera: Any, n: int, lights: LightSampler, gen: torch.Generator) -> DistanceReservoirs:
        """Each camera ray's RIS over ``distance_candidates`` pairs ``(t, y)`` (class docstring)."""
        r = self.rays(camera, n, gen)
        m = self.settings.distance_candidates
        u = torch.rand(n, 6 * m + 1, generator=gen, device=r.o.device)
        ws, ps, ts, ks, om = [], [], [], [], []
        for j in range(m):
            t = self.sample_distance(r, u[:, 6 * j], u[:, 6 * j + 1])
            ls = lights.sample(r.o + t[:, None] * r.d, u[:, 6 * j + 2:6 * j + 6])
            p, factor = self._dtarget(lights, t, ls.light, ls.wi, r)
            pt = self.distance_pdf(r, t)
            w = luminance3(ls.weight.unbind(1)) * factor / pt.clamp(min=1e-30)  # p_hat / (p_t p_src)
            ws.append(torch.where(pt > 0, w, torch.zeros_like(w)))
            ps.append(p)
            ts.append(t)
            ks.append(ls.light)
            om.append(ls.wi)
        sel, W, M = finish_ris(ws, ps, u[:, 6 * m], r.valid)
        return replace(r, t=gather(ts, sel), light=gather(ks, sel), omega=gather(om, sel), W=W, M=M)

    def shade(self, res: Any, rec: Any, lights: LightSampler, transmittance: Any, grid: Any,
              majorants: Any, gen: torch.Generator, batch: int) -> Tensor:
        """``sigma_s T(ta, t) HG L T(x_t -> y) W`` ``(N, 3)`` of each reservoir's pair on its own camera ray."""
        out = torch.zeros(len(res.W), 3, device=res.o.device)
        idx = (res.valid & (res.W > 0)).nonzero().squeeze(1)
        for a in range(0, len(idx), batch):
            i = idx[a:a + batch]
            r = res.take(i)
            x = r.o + r.t[:, None] * r.d
            wi, dist, c, _ = lights.evaluate(r.light, r.omega, x)
            w = self.albedo * grid.sigma_t(x) * hg_pdf(self.g, (r.d * wi).sum(-1)) * r.W
            t_cam = r.transmittance(grid, r.t, self.CAMERA_POINTS, gen)
            t1 = torch.minimum(grid.box.intersect(x, wi)[1], dist)
            shadow = ExtinctionTable.march(grid.sigma_t, x, wi, torch.zeros_like(t1), t1, self.LIGHT_STEPS)
            t_light = shadow.transmittance(grid, t1, self.LIGHT_POINTS, gen)
            out[i] = c * (w * t_cam * t_light)[:, None]
        return out
