"""Equi-angular distance sampling for point lights (Kulla and Fajardo 2012), ``renderer.point_light_sampling``.

Along a flight segment ``x(t) = o + t d``, ``t in [ta, tb]``, with throughput ``beta``, the direct light a point
light (position ``p``, intensity ``I``) scatters towards ``-d`` is the integral

    D = int_ta^tb T(o, x(t)) sigma_s(x(t)) p(d, w_l) I / r(t)^2 T(x(t), p) dt,

``r(t) = |p - x(t)|``, ``w_l`` the unit direction from ``x(t)`` to ``p``. Equi-angular sampling draws ``t`` with
pdf ``h / (A (h^2 + (t - Delta)^2))`` (``Delta`` the ray parameter closest to ``p``, ``h`` the distance of ``p``
from the ray, ``A`` the angle the sampled part of the segment subtends at ``p``), which cancels the ``1/r^2``.
Two factors of the integrand are added to it here. The phase value: with ``theta = atan((t - Delta) / h)`` the
cosine towards the light is ``-sin theta``, so sampling ``theta`` in proportion to ``p_HG(-sin theta)`` (a table,
:class:`PhaseAngleTable`) cancels the phase function too -- for ``g = 0.8`` it varies 729-fold along a ray, and
plain equi-angular sampling was measured *less* efficient than next-event estimation there. And the density at
brick resolution: the pdf follows the bricks the segment crosses
(:func:`nrc.transport.tracking.majorant_segments`, the one brick walk of the eager code), in brick ``k``
``m_k p(theta) (dtheta/dt) / W`` with ``m_k`` the brick's majorant and ``W`` the sum over the bricks of ``m_k``
times the phase integral over their angles; empty bricks, where ``sigma_s`` is zero, are never sampled. What
is left in the estimate is ``beta (sigma_s(x) / m_k) I T(o, x) T(x, p) W / h``: bounded but for ``1/h``, the
glow of a ray passing next to the light. Both transmittances are estimated by the configured
transmittance estimator (independent, unbiased estimates: their product is unbiased); ``sigma_s`` is the exact
density. One point light per segment is chosen, with probability proportional to its power into the medium's
bounding sphere (:func:`nrc.transport.light_sampling.light_powers`).

Why equi-angular alone, with no MIS against the next-event estimate at delta-tracked vertices (option (a) of
issue 16): the delta-tracking pdf of a vertex, ``sigma_t T``, has no closed form in a heterogeneous medium, and
an *estimated* transmittance inside a MIS weight makes the weights not sum to one, i.e. a biased combination.
So a point light's direct light is estimated only here, on every segment of a path (camera ray and scattering
rays up to the one that leads to vertex ``max_scatter``), and the renderers leave the point lights out of the
next-event estimate at the vertices (:meth:`LightSampler.for_scene`, ``exclude_points``). The two estimators
split the integrand, not weight it: the vertex estimates everything but the point lights' direct light, this
module estimates that. Every vertex the path reaches sits on a segment, so nothing is counted twice or missed.

Memory: per batch of ``N`` segments, ``K`` ``(N,)`` floats for the ``K`` brick crossings of the longest
segment (``K <= bx + by + bz``; a run of empty bricks is one), and the estimator's own state for ``2N`` rays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.transport.light_sampling import light_powers
from nrc.transport.lights import PointLight
from nrc.transport.phase import hg_pdf
from nrc.transport.tracking import majorant_segments
from nrc.volume.majorant import MajorantGrid

H_MIN = 1e-4  # the light's distance from the ray is clamped to H_MIN x brick size (sampling and pdf alike)


class PhaseAngleTable:
    """The HG phase value along a ray as a function of the equi-angular angle, tabulated for sampling.

    With ``theta = atan((t - Delta) / h)`` the cosine between the ray's direction ``d`` and the direction to the
    light is ``-sin(theta)``, so the integrand's phase factor is ``p_HG(g, -sin theta)``. The table holds it
    piecewise constant on ``n`` cells of ``[-pi/2, pi/2]`` (the value at each cell's midpoint) and its running
    integral ``C`` (piecewise linear); sampling inverts ``C`` exactly and :meth:`density` is the derivative of
    that ``C``, so the pdf is the one the samples follow (the table's accuracy affects variance, never bias).
    For ``g = 0`` it is constant: plain equi-angular sampling.

    Args:
        g: the HG asymmetry in ``(-1, 1)``; n: cells (memory ``2n`` floats).
    """

    def __init__(self, g: float, device: torch.device, n: int = 4096) -> None:
        self.n, self.step = n, math.pi / n
        mid = -0.5 * math.pi + (torch.arange(n, dtype=torch.float64) + 0.5) * self.step
        v = hg_pdf(float(g), -torch.sin(mid))
        self.value = v.float().to(device)
        self.cum = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(v * self.step, 0)]).float().to(device)

    def _cell(self, theta: Tensor) -> Tensor:
        return ((theta + 0.5 * math.pi) / self.step).floor().long().clamp(0, self.n - 1)

    def cdf(self, theta: Tensor) -> Tensor:
        """``C(theta)``: the integral of the tabulated phase from ``-pi/2`` (``(N,)``)."""
        i = self._cell(theta)
        lo = -0.5 * math.pi + i.to(theta.dtype) * self.step
        return self.cum[i] + self.value[i] * (theta - lo)

    def inverse(self, c: Tensor) -> Tensor:
        """The angle ``theta`` with ``C(theta) = c``."""
        i = (torch.searchsorted(self.cum, c.contiguous(), right=True) - 1).clamp(0, self.n - 1)
        lo = -0.5 * math.pi + i.to(c.dtype) * self.step
        return lo + ((c - self.cum[i]) / self.value[i]).clamp(0.0, self.step)

    def density(self, theta: Tensor) -> Tensor:
        """``dC / dtheta`` at ``theta``."""
        return self.value[self._cell(theta)]


@dataclass
class EquiangularSegments:
    """The sampled parts of each segment: ``(N,)`` tensors ``delta``, ``h``, the total weight ``W``, and per
    brick crossing ``k`` the lists ``t0[k]``, ``t1[k]``, ``weight[k]`` (the brick's majorant ``m[k]`` x the
    tabulated phase integral over the angles of its part; zero for empty bricks)."""

    table: PhaseAngleTable
    delta: Tensor
    h: Tensor
    total: Tensor
    t0: list[Tensor]
    t1: list[Tensor]
    weight: list[Tensor]
    majorant: list[Tensor]

    def density(self, m: Tensor, t: Tensor) -> Tensor:
        """Pdf at ``t`` inside a part of majorant ``m``: ``m p(theta) (dtheta / dt) / W``."""
        x = t - self.delta
        theta = torch.atan(x / self.h)
        dens = m * self.table.density(theta) * self.h / (self.total.clamp(min=1e-30) * (self.h * self.h + x * x))
        return torch.where(self.total > 0, dens, torch.zeros_like(t))

    def pdf(self, t: Tensor) -> Tensor:
        """Pdf ``(N,)`` of the distance ``t`` (zero outside the sampled parts)."""
        m = torch.zeros_like(t)
        for a, b, w, mk in zip(self.t0, self.t1, self.weight, self.majorant):
            m = torch.where((w > 0) & (t >= a) & (t <= b), mk, m)
        return self.density(m, t)


def segments(majorants: MajorantGrid, o: Tensor, d: Tensor, ta: Tensor, tb: Tensor, p: Tensor,
             table: PhaseAngleTable) -> EquiangularSegments:
    """The sampling measure of segments ``o + t d``, ``t in [ta, tb]`` (``(N, 3)``, ``(N,)``), towards the light
    positions ``p`` ``(N, 3)``."""
    rel = p - o
    delta = (rel * d).sum(-1)
    h = torch.linalg.vector_norm(rel - delta[:, None] * d, dim=-1).clamp(min=H_MIN * majorants.brick_size)
    t0s, t1s, weights, majs = [], [], [], []
    total = torch.zeros_like(ta)
    for _, a, b, m, _ in majorant_segments(majorants, o, d, ta, tb):
        c = table.cdf(torch.atan((b - delta) / h)) - table.cdf(torch.atan((a - delta) / h))
        w = torch.where(m > 0, c.clamp(min=0.0) * m, torch.zeros_like(a))
        t0s.append(a)
        t1s.append(b)
        weights.append(w)
        majs.append(m)
        total = total + w
    return EquiangularSegments(table, delta, h, total, t0s, t1s, weights, majs)


def sample_distance(seg: EquiangularSegments, u: Tensor) -> tuple[Tensor, Tensor]:
    """``(t, pdf)`` ``(N,)`` from uniforms ``u`` ``(N,)``: the brick part by its weight, then ``t`` inside it by
    inverting the tabulated phase integral over its angles (``pdf = 0`` and ``t = delta`` where nothing is
    sampled)."""
    target = u * seg.total
    run = torch.zeros_like(u)
    t = seg.delta.clone()
    m = torch.zeros_like(u)
    picked = torch.zeros_like(u, dtype=torch.bool)
    for a, b, w, mk in zip(seg.t0, seg.t1, seg.weight, seg.majorant):
        take = ~picked & (w > 0) & ((target < run + w) | (run + w >= seg.total))
        c0 = seg.table.cdf(torch.atan((a - seg.delta) / seg.h))
        theta = seg.table.inverse(c0 + ((target - run) / mk.clamp(min=1e-30)).clamp(min=0.0))
        ti = seg.delta + seg.h * torch.tan(theta.clamp(-0.5 * math.pi + 1e-7, 0.5 * math.pi - 1e-7))
        t = torch.where(take, torch.minimum(torch.maximum(ti, a), b), t)
        m = torch.where(take, mk, m)
        picked = picked | take
        run = run + w
    return t, torch.where(picked, seg.density(m, t), torch.zeros_like(t))


class EquiangularSampler:
    """Point lights' direct light along flight segments (module docstring).

    Args:
        points: the scene's point lights (at least one).
        grid: the density grid; majorants: its brick majorants (the sampled parts, and the estimator's).
        albedo, g: the medium's albedo and HG asymmetry.
        transmittance: the configured estimator (``make_transmittance``; :meth:`contribution` passes it a
            generator). Built once per scene (the phase table, the light choice), used by every frame.
    """

    def __init__(self, points: tuple[PointLight, ...], grid: Any, majorants: MajorantGrid, albedo: float, g: float,
                 transmittance: Any) -> None:
        if not points:
            raise ValueError("equi-angular sampling needs at least one point light")
        self.grid, self.majorants, self.albedo, self.g = grid, majorants, float(albedo), float(g)
        self.transmittance = transmittance
        dev = grid.device
        self.positions = torch.stack([lt.position for lt in points]).to(dev)
        self.intensities = torch.stack([lt.intensity for lt in points]).to(dev)
        box = grid.box
        powers = light_powers(points, (box.lo + box.hi) / 2, float(torch.linalg.vector_norm(box.hi - box.lo)) / 2)
        total = sum(powers)
        pmf = [pw / total for pw in powers] if total > 0 else [1.0 / len(points)] * len(points)
        self.pmf = torch.tensor(pmf, device=dev)
        self.cdf = torch.cumsum(self.pmf.double(), 0).float()
        self.cdf[-1] = 1.0
        self.table = PhaseAngleTable(self.g, dev)

    def contribution(self, o: Tensor, d: Tensor, ta: Tensor, tb: Tensor, beta: Tensor, u: Tensor,
                     gen: torch.Generator) -> Tensor:
        """RGB ``(N, 3)``: ``beta`` x the estimate of one chosen point light's direct light scattered along the
        segments (``o``, ``d`` ``(N, 3)`` unit, ``[ta, tb]`` inside the box, ``u`` ``(N, 2)`` uniforms)."""
        k = torch.searchsorted(self.cdf, u[:, 0].contiguous(), right=True).clamp(max=len(self.cdf) - 1)
        p, inten, sel = self.positions[k], self.intensities[k], self.pmf[k]
        seg = segments(self.majorants, o, d, ta, tb, p, self.table)
        t, pdf = sample_distance(seg, u[:, 1])
        ok = pdf > 0
        x = o + t[:, None] * d
        to = p - x
        r2 = (to * to).sum(-1).clamp(min=1e-12)
        r = torch.sqrt(r2)
        wl = to / r[:, None]
        sigma_s = self.albedo * self.grid.sigma_t(x)
        t_out = torch.minimum(self.grid.box.intersect(x, wl)[1], r)
        # the two transmittances in one estimator call: o -> x along d, x -> the light
        T = self.transmittance(self.grid, self.majorants, torch.cat([o, x]), torch.cat([d, wl]),
                               torch.cat([ta, torch.zeros_like(t)]), torch.cat([t, t_out]), gen)
        n = len(t)
        w = sigma_s * hg_pdf(self.g, (d * wl).sum(-1)) * T[:n] * T[n:] / (pdf.clamp(min=1e-30) * r2 * sel)
        return torch.where(ok[:, None], beta * inten * w[:, None], torch.zeros_like(beta))
