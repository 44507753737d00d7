"""Next-event estimation: sampling the scene's lights, and the environment's radiance and pdf for MIS.

One light is chosen among the lights the scene has (no light, no shadow rays), by ``renderer.light_selection``:

* ``uniform``: each with probability ``1 / n``;
* ``power``: with probability proportional to the power the light sends into the medium's bounding sphere
  (centre ``c``, radius ``R`` of the grid's box), in luminance (Rec. 709) of the RGB values
  (:func:`light_powers`): a directional light ``pi R^2 E``; a point light at distance ``r > R`` from ``c``
  ``I 2 pi (1 - sqrt(1 - R^2 / r^2))`` (the solid angle the sphere subtends), inside the sphere ``4 pi I``;
  a uniform sky ``pi R^2 4 pi L``; a lat-long map ``pi R^2`` times its radiance integrated over the sphere.
  Lights that send nothing are never chosen; when none sends anything the choice is uniform.

For the chosen light a direction ``wi`` (unit, from the shading point towards the light) is produced with:

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
SELECTIONS = ("uniform", "power")


def _lum(rgb: Tensor) -> float:
    return float((rgb.double().cpu() * torch.tensor(_LUMINANCE, dtype=torch.float64)).sum())


def light_powers(lights: tuple[Light, ...], centre: Tensor, radius: float) -> list[float]:
    """Luminance power each light sends into the sphere ``(centre, radius)``, in :class:`LightSampler`'s light
    order (directional, point, the uniform skies together, then each lat-long map; module docstring)."""
    area = math.pi * radius * radius
    out = [area * _lum(lt.irradiance) for lt in lights if isinstance(lt, DirectionalLight)]
    for lt in lights:
        if isinstance(lt, PointLight):
            r = float(torch.linalg.vector_norm((lt.position - centre).double().cpu()))
            solid = 4.0 * math.pi if r <= radius else 2.0 * math.pi * (1.0 - math.sqrt(1.0 - (radius / r) ** 2))
            out.append(_lum(lt.intensity) * solid)
    envs = [lt for lt in lights if isinstance(lt, EnvironmentLight)]
    uniform = [e for e in envs if e.radiance is not None]
    if uniform:
        out.append(area * 4.0 * math.pi * sum(_lum(e.radiance) * e.scale for e in uniform))
    for e in envs:
        if e.image is not None:
            h, w = e.image.shape[:2]
            theta = (torch.arange(h, dtype=torch.float64) + 0.5) / h * math.pi
            d_omega = (2.0 * math.pi / w) * (math.pi / h) * torch.sin(theta)  # (H,) solid angle of a pixel
            lum = (e.image.double().cpu() * torch.tensor(_LUMINANCE, dtype=torch.float64)).sum(-1) * e.scale
            out.append(area * float((lum * d_omega[:, None]).sum()))
    return out


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
    """Samples one of the scene's lights (``selection``); evaluates the environment for escaping paths.

    Args:
        lights: the scene's lights (any number, including none).
        selection: ``uniform`` or ``power`` (module docstring).
        bounds: ``(lo, hi)`` of the medium's box, for ``power``.
    """

    def __init__(self, lights: tuple[Light, ...], device: torch.device, selection: str = "uniform",
                 bounds: tuple[Tensor, Tensor] | None = None) -> None:
        if selection not in SELECTIONS:
            raise ValueError(f"light selection must be one of {', '.join(SELECTIONS)}, got {selection!r}")
        if selection == "power" and bounds is None:
            raise ValueError("power light selection needs the medium's bounds")
        self.device = device
        self.lights = tuple(lights)
        self.selection, self.bounds = selection, bounds
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
        # selection probabilities in light order (directional, point, uniform sky, maps)
        self.pmf = [1.0 / self.n_lights] * self.n_lights if self.n_lights else []
        if selection == "power" and self.n_lights:
            lo, hi = bounds
            powers = light_powers(self.lights, (lo + hi) / 2, float(torch.linalg.vector_norm(hi - lo)) / 2)
            total = sum(powers)
            if total > 0:
                self.pmf = [pw / total for pw in powers]
        self._pmf = torch.tensor(self.pmf or [1.0], device=device)
        self._cdf = torch.cumsum(self._pmf.double(), 0).float()

    @classmethod
    def for_scene(cls, scene, selection: str = "uniform") -> LightSampler:
        """The sampler of a scene's lights, bounded by its medium's box."""
        box = scene.grid.box
        return cls(scene.lights, scene.device, selection, (box.lo, box.hi))

    def with_lights(self, lights: tuple[Light, ...]) -> LightSampler:
        """The same selection for other lights (an animated sun)."""
        return LightSampler(lights, self.device, self.selection, self.bounds)

    @property
    def env_select(self) -> list[float]:
        """Selection probabilities of the environment lights: the uniform sky (if any), then each map."""
        return self.pmf[len(self.directional) + len(self.points):]

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
        sel = iter(self.env_select)
        if self.has_uniform_env:
            pdf = pdf + next(sel) / (4.0 * math.pi)
        for m in self.env_maps:
            pdf = pdf + next(sel) * m.pdf(d)
        return pdf

    def sample(self, x: Tensor, u: Tensor) -> LightSample:
        """Sample one light per point ``x`` ``(N, 3)`` with uniforms ``u`` ``(N, 4)``; requires ``n_lights > 0``."""
        n = x.shape[0]
        if self.selection == "uniform":
            k = (u[:, 0] * self.n_lights).long().clamp(max=self.n_lights - 1)
        else:
            k = torch.searchsorted(self._cdf, u[:, 0].contiguous(), right=True).clamp(max=self.n_lights - 1)
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
            own_fix = torch.where(m, (pdf_drawn - emap.pdf(d)) * self.pmf[idx], own_fix)
            is_env = is_env | m
            idx += 1
        # 1 / P(select) of the delta lights' samples
        inv_select = torch.full((n,), float(self.n_lights), device=x.device) if self.selection == "uniform" \
            else 1.0 / self._pmf[k].clamp(min=1e-30)
        if self.has_env:
            # Environment samples: balance heuristic over all environment lights, i.e. the total
            # environment radiance over the summed pdf (which includes P(select)).
            pdf = self.env_pdf(wi) + own_fix
            light_pdf = torch.where(is_env, pdf, light_pdf)
            env_w = self.env_radiance(wi) / pdf.clamp(min=1e-30)[:, None]
            weight = torch.where(is_env[:, None], env_w, weight * inv_select[:, None])
        else:
            weight = weight * inv_select[:, None]
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
    direction, ``P(select sky) / (4 pi)``; with ``power`` selection (and several lights) then every light's
    selection probability, in light order (the uniform choice needs none).

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
        self.selection = lights.selection if lights.n_lights > 1 else "uniform"
        vals: list[float] = []
        for lt in lights.directional:
            vals += [float(v) for v in (-lt.direction).tolist()] + [float(v) for v in lt.irradiance.tolist()]
        for lt in lights.points:
            vals += [float(v) for v in lt.position.tolist()] + [float(v) for v in lt.intensity.tolist()]
        if self.has_uniform_env:
            vals += [float(v) for v in lights.uniform_env.tolist()] + [lights.env_select[0] / (4.0 * math.pi)]
        if self.selection == "power":
            vals += [float(p) for p in lights.pmf]
        self.values = vals

    @property
    def structure(self) -> tuple:
        """What a compiled step depends on: ``(directional lights, point lights, uniform sky)``, and ``"power"``
        for the power selection of several lights."""
        base = (self.n_directional, self.n_points, self.has_uniform_env)
        return (*base, "power") if self.selection == "power" else base

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
        power = self.selection == "power"
        if power:  # the selection probabilities are the last n values; k = the number of CDF steps below u
            pmf = values[len(values) - n:]
            acc, k = pmf[0], torch.zeros_like(x[0], dtype=torch.long)
            for j in range(1, n):
                k = k + (u[0] >= acc).long()
                acc = acc + pmf[j]
            inv = pmf[n - 1] + torch.zeros_like(x[0])
            for j in range(n - 1):
                inv = torch.where(k == j, pmf[j] + torch.zeros_like(x[0]), inv)
            inv = 1.0 / inv.clamp(min=1e-30)
            lane = 1
        elif n > 1:
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
            weight = tuple(torch.where(is_env, e / pdf + zero, w * (inv if power else n)) for e, w in zip(env, weight))
        else:
            light_pdf = zero
            weight = tuple(w * (inv if power else n) for w in weight)
        return wi, dist, weight, light_pdf, is_env
