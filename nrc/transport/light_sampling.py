"""Next-event estimation: sampling the scene's lights, and the environment's radiance and pdf for MIS.

One light is chosen uniformly among the lights the scene has (no light, no shadow rays). For the chosen
light a direction ``wi`` (unit, from the shading point towards the light) is produced with:

* directional: ``wi = -direction`` (a delta distribution), weight ``irradiance``;
* point: ``wi`` towards the position, distance ``r``, weight ``intensity / r^2``;
* environment: ``wi`` from the uniform sphere (uniform sky) or from the image's piecewise-constant
  distribution (lat-long image, proportional to luminance x sin(theta) per pixel), weight ``L(wi) / pdf``.

The returned ``weight`` already includes ``1 / P(select)``; the caller multiplies by the phase function,
the transmittance to the light and, for environment samples, the MIS weight (power heuristic against
phase sampling, whose escape contributions use :meth:`LightSampler.env_pdf`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from nrc.transport.lights import DirectionalLight, EnvironmentLight, Light, PointLight

_LUMINANCE = (0.2126, 0.7152, 0.0722)


def direction_to_latlong(d: Tensor) -> tuple[Tensor, Tensor]:
    """Unit directions ``(N, 3)`` -> lat-long ``(u, v)`` in ``[0, 1)`` x ``[0, 1]`` (SCENE.md mapping)."""
    u = torch.atan2(d[:, 0], -d[:, 2]) / (2.0 * math.pi)
    u = u - torch.floor(u)
    v = torch.acos(d[:, 1].clamp(-1.0, 1.0)) / math.pi
    return u, v


def latlong_to_direction(u: Tensor, v: Tensor) -> Tensor:
    """Inverse of :func:`direction_to_latlong`."""
    phi, theta = 2.0 * math.pi * u, math.pi * v
    s = torch.sin(theta)
    return torch.stack([s * torch.sin(phi), torch.cos(theta), -s * torch.cos(phi)], dim=-1)


def uniform_sphere(u: Tensor) -> Tensor:
    """Uniform directions on the unit sphere from ``u`` ``(N, 2)`` in ``[0, 1)^2`` (pdf ``1 / 4pi``)."""
    z = 1.0 - 2.0 * u[:, 0]
    r = torch.sqrt((1.0 - z * z).clamp(min=0.0))
    phi = 2.0 * math.pi * u[:, 1]
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


class EnvironmentMap:
    """Lat-long environment radiance with bilinear lookup and importance sampling.

    Args:
        image: ``(H, W, 3)`` radiance, row 0 straight up, column 0 facing -z.
        scale: multiplier of the radiance.
    """

    def __init__(self, image: Tensor, scale: float) -> None:
        self.image = image * scale
        self.h, self.w = image.shape[:2]
        lum = (self.image * torch.tensor(_LUMINANCE, device=image.device)).sum(-1)
        theta = (torch.arange(self.h, device=image.device) + 0.5) / self.h * math.pi
        weights = (lum * torch.sin(theta)[:, None]).reshape(-1).double()
        total = float(weights.sum())
        if total <= 0:  # a black map: sample uniformly (its radiance is zero anyway)
            weights = torch.ones_like(weights)
            total = float(weights.numel())
        self.pmf = (weights / total).float()
        self.cdf = torch.cumsum(weights / total, 0).float()
        self.cdf[-1] = 1.0

    def radiance(self, d: Tensor) -> Tensor:
        """Bilinear radiance ``(N, 3)`` for unit directions ``d`` (wraps in u, clamps in v)."""
        u, v = direction_to_latlong(d)
        x = u * self.w - 0.5
        y = (v * self.h - 0.5).clamp(0.0, self.h - 1.0)
        x0 = torch.floor(x)
        y0 = torch.floor(y).clamp(max=max(self.h - 2, 0))
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0i = x0.long() % self.w
        x1i = (x0i + 1) % self.w
        y0i = y0.long()
        y1i = (y0i + 1).clamp(max=self.h - 1)
        img = self.image
        top = img[y0i, x0i] * (1 - fx) + img[y0i, x1i] * fx
        bot = img[y1i, x0i] * (1 - fx) + img[y1i, x1i] * fx
        return top * (1 - fy) + bot * fy

    def sample(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Sample ``(direction (N, 3), solid-angle pdf (N,))`` from ``u`` ``(N, 3)`` in ``[0, 1)^3``."""
        idx = torch.searchsorted(self.cdf, u[:, 0].contiguous(), right=True).clamp(max=self.cdf.numel() - 1)
        row, col = idx // self.w, idx % self.w
        uu = (col.to(u.dtype) + u[:, 1]) / self.w
        vv = (row.to(u.dtype) + u[:, 2]) / self.h
        d = latlong_to_direction(uu, vv)
        return d, self._pdf_of_pixel(idx, vv)

    def pdf(self, d: Tensor) -> Tensor:
        """Solid-angle pdf ``(N,)`` with which :meth:`sample` produces unit directions ``d``."""
        u, v = direction_to_latlong(d)
        col = (u * self.w).long().clamp(0, self.w - 1)
        row = (v * self.h).long().clamp(0, self.h - 1)
        return self._pdf_of_pixel(row * self.w + col, v)

    def _pdf_of_pixel(self, idx: Tensor, v: Tensor) -> Tensor:
        sin_theta = torch.sin(math.pi * v).clamp(min=1e-7)
        return self.pmf[idx] * (self.w * self.h) / (2.0 * math.pi**2 * sin_theta)


@dataclass
class LightSample:
    """One next-event sample per shading point (all ``(N, ...)`` tensors)."""

    wi: Tensor  # (N, 3) unit direction towards the light
    distance: Tensor  # (N,) distance to the light (inf for directional and environment)
    weight: Tensor  # (N, 3) light contribution / (pdf * P(select)), without phase and transmittance
    light_pdf: Tensor  # (N,) P(select) * solid-angle pdf for environment samples, 0 for delta lights
    is_env: Tensor  # (N,) bool: an environment sample (MIS applies)


class LightSampler:
    """Samples the scene's lights uniformly; evaluates the environment for escaping paths.

    Args:
        lights: the scene's lights (any number, including none).
    """

    def __init__(self, lights: tuple[Light, ...], device: torch.device) -> None:
        self.device = device
        self.directional = [lt for lt in lights if isinstance(lt, DirectionalLight)]
        self.points = [lt for lt in lights if isinstance(lt, PointLight)]
        envs = [lt for lt in lights if isinstance(lt, EnvironmentLight)]
        self.uniform_env = torch.zeros(3, device=device)  # sum of all uniform skies
        self.env_maps = [EnvironmentMap(e.image, e.scale) for e in envs if e.image is not None]
        for e in envs:
            if e.radiance is not None:
                self.uniform_env = self.uniform_env + e.radiance * e.scale
        # Uniform skies are merged into one light (their sum); each map is its own light.
        self.has_uniform_env = any(e.radiance is not None for e in envs)
        self.n_lights = len(self.directional) + len(self.points) + int(self.has_uniform_env) + len(self.env_maps)
        self.has_env = self.has_uniform_env or bool(self.env_maps)

    def env_radiance(self, d: Tensor) -> Tensor:
        """Environment radiance ``(N, 3)`` arriving from unit directions ``d`` (zero without environment)."""
        out = self.uniform_env.expand(d.shape[0], 3)
        for m in self.env_maps:
            out = out + m.radiance(d)
        return out

    def env_pdf(self, d: Tensor) -> Tensor:
        """``P(select) x`` solid-angle pdf ``(N,)`` of NEE producing ``d`` from any environment light."""
        pdf = torch.zeros(d.shape[0], device=d.device)
        if self.n_lights == 0:
            return pdf
        if self.has_uniform_env:
            pdf = pdf + 1.0 / (4.0 * math.pi)
        for m in self.env_maps:
            pdf = pdf + m.pdf(d)
        return pdf / self.n_lights

    def sample(self, x: Tensor, u: Tensor) -> LightSample:
        """Sample one light per point ``x`` ``(N, 3)`` with uniforms ``u`` ``(N, 4)``; requires ``n_lights > 0``."""
        n = x.shape[0]
        k = (u[:, 0] * self.n_lights).long().clamp(max=self.n_lights - 1)
        inf = torch.full((n,), float("inf"), device=x.device)
        wi = torch.zeros(n, 3, device=x.device)
        wi[:, 1] = 1.0
        dist, weight = inf.clone(), torch.zeros(n, 3, device=x.device)
        light_pdf = torch.zeros(n, device=x.device)
        is_env = torch.zeros(n, dtype=torch.bool, device=x.device)
        idx = 0
        for light in self.directional:
            m = (k == idx)[:, None]
            wi = torch.where(m, -light.direction, wi)
            weight = torch.where(m, light.irradiance.expand(n, 3), weight)
            idx += 1
        for light in self.points:
            m = k == idx
            to = light.position - x
            r2 = (to * to).sum(-1).clamp(min=1e-12)
            r = torch.sqrt(r2)
            wi = torch.where(m[:, None], to / r[:, None], wi)
            dist = torch.where(m, r, dist)
            weight = torch.where(m[:, None], light.intensity / r2[:, None], weight)
            idx += 1
        if self.has_uniform_env:
            m = k == idx
            d = uniform_sphere(u[:, 1:3])
            wi = torch.where(m[:, None], d, wi)
            is_env = is_env | m
            idx += 1
        # Pdf correction for map samples: use the pdf the sample was drawn with (re-evaluating it from
        # the direction can round into a neighbouring pixel at pixel borders).
        own_fix = torch.zeros(n, device=x.device)
        for emap in self.env_maps:
            m = k == idx
            d, pdf_drawn = emap.sample(u[:, 1:4])
            wi = torch.where(m[:, None], d, wi)
            own_fix = torch.where(m, (pdf_drawn - emap.pdf(d)) / self.n_lights, own_fix)
            is_env = is_env | m
            idx += 1
        if self.has_env:
            # Environment samples: balance heuristic over all environment lights, i.e. the total
            # environment radiance over the summed pdf (which includes P(select)).
            pdf = self.env_pdf(wi) + own_fix
            light_pdf = torch.where(is_env, pdf, light_pdf)
            env_w = self.env_radiance(wi) / pdf.clamp(min=1e-30)[:, None]
            weight = torch.where(is_env[:, None], env_w, weight * self.n_lights)
        else:
            weight = weight * self.n_lights
        return LightSample(wi, dist, weight, light_pdf, is_env)


def power_heuristic(a: Tensor, b: Tensor | float) -> Tensor:
    """Power heuristic ``a^2 / (a^2 + b^2)`` (elementwise), 1 where both are zero."""
    a2, b2 = a * a, b * b
    den = a2 + b2
    return torch.where(den > 0, a2 / den.clamp(min=1e-30), torch.ones_like(den))


def _pick(m: Tensor | None, new: tuple, old: tuple) -> tuple:
    """Component-wise ``where(m, new, old)``; ``m=None`` takes ``new`` (a light chosen with probability 1)."""
    if m is None:
        return tuple(n if isinstance(n, Tensor) and n.dim() else torch.zeros_like(o) + n for n, o in zip(new, old))
    return tuple(torch.where(m, n, o) for n, o in zip(new, old))


class LightTable:
    """:class:`LightSampler`'s uniform selection in the form a per-slot step consumes: the *structure* (how
    many directional and point lights, whether a uniform sky exists) is fixed, the lights' parameters are
    numbers in :attr:`values` that a compiled step takes as an input, so moving, recolouring or dimming a
    light does not recompile. Lat-long environment maps are not supported (:attr:`supported`).

    Layout of :attr:`values`: per directional light ``-direction (3), irradiance (3)``; per point light
    ``position (3), intensity (3)``; with a uniform sky its radiance ``(3)`` and the NEE pdf of any
    direction, ``1 / (4 pi n_lights)``.

    Args:
        lights: the sampler whose lights are read.
    """

    def __init__(self, lights: LightSampler) -> None:
        self.supported = not lights.env_maps
        self.n_directional = len(lights.directional)
        self.n_points = len(lights.points)
        self.has_uniform_env = lights.has_uniform_env
        self.n_lights = lights.n_lights
        self.has_env = lights.has_env
        vals: list[float] = []
        for lt in lights.directional:
            vals += [float(v) for v in (-lt.direction).tolist()] + [float(v) for v in lt.irradiance.tolist()]
        for lt in lights.points:
            vals += [float(v) for v in lt.position.tolist()] + [float(v) for v in lt.intensity.tolist()]
        if self.has_uniform_env:
            vals += [float(v) for v in lights.uniform_env.tolist()] + [1.0 / (4.0 * math.pi) / self.n_lights]
        self.values = vals

    @property
    def structure(self) -> tuple[int, int, bool]:
        """What a compiled step depends on: ``(directional lights, point lights, uniform sky)``."""
        return self.n_directional, self.n_points, self.has_uniform_env

    @property
    def lanes(self) -> int:
        """Uniforms :meth:`sample` uses: the light choice (several lights) and a sky direction (2)."""
        return (self.n_lights > 1) + 2 * self.has_uniform_env

    def sample(self, values: list, x: tuple, u: list) -> tuple[tuple, Tensor, tuple, Tensor, Tensor]:
        """``(wi, distance, weight, light_pdf, is_env)`` as :meth:`LightSampler.sample`, in component form,
        with :attr:`values` as numbers or 0-d tensors and ``u`` the :attr:`lanes` uniforms."""
        n = self.n_lights
        lane = 0
        k = None
        if n > 1:
            k = (u[0] * n).long().clamp(max=n - 1)
            lane = 1
        zero = torch.zeros_like(x[0])
        wi: tuple = (zero, zero + 1.0, zero)
        dist = torch.full_like(zero, math.inf)
        weight: tuple = (zero, zero, zero)
        is_env = torch.zeros_like(zero, dtype=torch.bool)
        idx, pos = 0, 0
        for _ in range(self.n_directional):
            m = None if k is None else k == idx
            wi, weight = _pick(m, tuple(values[pos:pos + 3]), wi), _pick(m, tuple(values[pos + 3:pos + 6]), weight)
            idx, pos = idx + 1, pos + 6
        for _ in range(self.n_points):
            m = None if k is None else k == idx
            p, inten = values[pos:pos + 3], values[pos + 3:pos + 6]
            to = (p[0] - x[0], p[1] - x[1], p[2] - x[2])
            r2 = (to[0] * to[0] + to[1] * to[1] + to[2] * to[2]).clamp(min=1e-12)
            r = torch.sqrt(r2)
            wi = _pick(m, (to[0] / r, to[1] / r, to[2] / r), wi)
            dist = r if m is None else torch.where(m, r, dist)
            weight = _pick(m, (inten[0] / r2, inten[1] / r2, inten[2] / r2), weight)
            idx, pos = idx + 1, pos + 6
        if self.has_uniform_env:
            m = None if k is None else k == idx
            z = 1.0 - 2.0 * u[lane]
            rr = torch.sqrt((1.0 - z * z).clamp(min=0.0))
            phi = 2.0 * math.pi * u[lane + 1]
            wi = _pick(m, (rr * torch.cos(phi), rr * torch.sin(phi), z), wi)
            is_env = torch.ones_like(is_env) if m is None else m
            env, pdf = values[pos:pos + 3], values[pos + 3]
            light_pdf = torch.where(is_env, zero + pdf, zero)
            weight = tuple(torch.where(is_env, e / pdf + zero, w * n) for e, w in zip(env, weight))
        else:
            light_pdf = zero
            weight = tuple(w * n for w in weight)
        return wi, dist, weight, light_pdf, is_env
