"""Next-event estimation: choosing one of the scene's lights, sampling it, and the environment's radiance and pdf
for MIS.

One light is chosen among the lights the scene has (no light, no shadow rays), by ``renderer.light_selection``:

* ``uniform``: each with probability ``1 / n``;
* ``power``: with probability proportional to the power the light sends into the medium's bounding sphere
  (centre ``c``, radius ``R`` of the grid's box), in luminance (Rec. 709) of the RGB values
  (:func:`light_powers`): a directional light ``pi R^2 E``; a point light at distance ``r > R`` from ``c``
  ``I 2 pi (1 - sqrt(1 - R^2 / r^2))`` (the solid angle the sphere subtends), inside the sphere ``4 pi I``;
  a uniform sky ``pi R^2 4 pi L``; a lat-long map ``pi R^2`` times its radiance integrated over the sphere.
  Lights that send nothing are never chosen; when none sends anything the choice is uniform.
* ``ris`` (``renderer.ris.candidates`` = ``M``): resampled importance sampling of ``M`` candidates of the
  ``power`` choice (:mod:`nrc.transport.ris`).

For the chosen light a direction ``wi`` (unit, from the shading point towards the light) is produced with:

* directional: ``wi = -direction`` (a delta distribution), weight ``irradiance``;
* point: ``wi`` towards the position, distance ``r``, weight ``intensity / r^2``;
* environment: ``wi`` from the uniform sphere (uniform sky) or from the image's piecewise-constant
  distribution (lat-long image, :class:`~nrc.transport.environment.EnvironmentMap`), weight ``L(wi) / pdf``.

The returned ``weight`` already includes ``1 / P(select)``; the caller multiplies by the phase function,
the transmittance to the light and, for environment samples, the MIS weight (:func:`power_heuristic` against
phase sampling, whose escape contributions use :meth:`LightSampler.env_pdf`).

One owner: :class:`LightTable` holds the choice and the geometry (component form, the lights' numbers as an input
of the compiled step); :class:`LightSampler` (rows) adds the lat-long maps and the environment's pdf and radiance
on top of the same code; :func:`~nrc.transport.ris.resample` is RIS for both.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from nrc.transport.environment import EnvironmentMap, sphere_direction, uniform_sphere
from nrc.transport.lights import LUMINANCE, DirectionalLight, EnvironmentLight, Light, PointLight
from nrc.transport.ris import Candidate, resample

SELECTIONS = ("uniform", "power", "ris")
POINT_LIGHT_SAMPLING = ("none", "equiangular")


@dataclass(frozen=True)
class LightSamplingSettings:
    """How the renderers sample lights: the ``renderer`` keys ``light_selection``, ``ris.candidates`` and
    ``point_light_sampling`` (``conf/renderer/shared/wavefront.yaml``, included by both
    renderers; one reader)."""

    selection: str = "uniform"
    """``uniform`` | ``power`` | ``ris`` (module docstring)."""
    candidates: int = 4
    """``ris``: candidates ``M`` per next-event estimate (``>= 1``; ignored by the other selections; measured in
    docs/measurements/path_tracer.md, "Light selection": 8 more efficient on many lights, 4 the default)."""
    point_lights: str = "none"
    """``none`` | ``equiangular``: point lights' direct light by equi-angular distance sampling along every
    flight segment instead of next-event estimation at the vertices (:mod:`nrc.transport.equiangular`)."""

    @classmethod
    def from_config(cls, cfg) -> LightSamplingSettings:
        """Read from a :class:`nrc.config.ConfigReader` of the ``renderer`` block (every key required: the defaults
        live in ``conf/renderer/shared/wavefront.yaml``)."""
        selection = cfg.get_choice("light_selection", list(SELECTIONS))
        ris = cfg.block("ris")
        candidates = ris.get_int("candidates", lo=1)
        ris.finish()
        point = cfg.get_choice("point_light_sampling", list(POINT_LIGHT_SAMPLING))
        return cls(selection, candidates, point)

    def equiangular_points(self, scene) -> tuple[PointLight, ...]:
        """The point lights sampled equi-angularly (all of them under ``equiangular``, none otherwise)."""
        if self.point_lights != "equiangular":
            return ()
        return tuple(lt for lt in scene.lights if isinstance(lt, PointLight))

    def metrics(self, sampler: LightSampler) -> dict:
        """What ``metrics.json`` (and TensorBoard's ``light/``) record of the light sampling: the settings, the
        lights the vertices' next-event estimate chooses among, and the entropy (bits) of that choice's
        probabilities (for ``ris``: of its source distribution; ``log2`` of the light count for ``uniform``)."""
        return {"light_selection": self.selection, "ris_candidates": self.candidates if self.selection == "ris" else 1,
                "point_light_sampling": self.point_lights, "nee_lights": sampler.n_lights,
                "light_selection_entropy_bits": sampler.entropy_bits,
                "light_selection_pmf": [round(float(p), 6) for p in sampler.pmf]}

    def sampler(self, scene) -> LightSampler:
        """The next-event sampler of ``scene``'s lights (without its point lights under ``equiangular``)."""
        return LightSampler.for_scene(scene, self.selection, self.candidates, self.point_lights == "equiangular")


def _lum(rgb: Tensor) -> float:
    return float((rgb.double().cpu() * torch.tensor(LUMINANCE, dtype=torch.float64)).sum())


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
            lum = (e.image.double().cpu() * torch.tensor(LUMINANCE, dtype=torch.float64)).sum(-1) * e.scale
            out.append(area * float((lum * d_omega[:, None]).sum()))
    return out


@dataclass
class LightSample:
    """One next-event sample per shading point (all ``(N, ...)`` tensors)."""

    wi: Tensor  # (N, 3) unit direction towards the light
    distance: Tensor  # (N,) distance to the light (inf for directional and environment)
    weight: Tensor  # (N, 3) light contribution / (pdf * P(select)), without phase and transmittance
    light_pdf: Tensor  # (N,) P(select) * solid-angle pdf for environment samples, 0 for delta lights
    is_env: Tensor  # (N,) bool: an environment sample (MIS applies)
    light: Tensor | None = None  # (N,) int64 index of the chosen light in light order (:meth:`LightSampler.evaluate`)


class LightSampler:
    """Samples one of the scene's lights (``selection``); evaluates the environment for escaping paths.

    Args:
        lights: the scene's lights (any number, including none).
        selection: ``uniform``, ``power`` or ``ris`` (module docstring; :meth:`sample` draws from the source
            distribution, ``power`` for ``ris``, whose resampling is :func:`~nrc.transport.ris.resample`).
        bounds: ``(lo, hi)`` of the medium's box, for ``power`` and ``ris``.
        candidates: ``ris``: candidates per estimate.
    """

    def __init__(self, lights: tuple[Light, ...], device: torch.device, selection: str = "uniform",
                 bounds: tuple[Tensor, Tensor] | None = None, candidates: int = 1) -> None:
        if selection not in SELECTIONS:
            raise ValueError(f"light selection must be one of {', '.join(SELECTIONS)}, got {selection!r}")
        if selection != "uniform" and bounds is None:
            raise ValueError(f"{selection} light selection needs the medium's bounds")
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
            raise ValueError(f"RIS candidates must be an integer >= 1, got {candidates!r}")
        self.device = device
        self.lights = tuple(lights)
        self.selection, self.bounds = selection, bounds
        self.candidates = candidates if selection == "ris" else 1
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
        if selection != "uniform" and self.n_lights:
            lo, hi = bounds
            powers = light_powers(self.lights, (lo + hi) / 2, float(torch.linalg.vector_norm(hi - lo)) / 2)
            total = sum(powers)
            if total > 0:
                self.pmf = [pw / total for pw in powers]
        self._pmf = torch.tensor(self.pmf or [1.0], device=device)
        # the one code of light choice and geometry (the compiled step's form; module docstring)
        self.table = LightTable(self)
        self._values = torch.tensor(self.table.values or [0.0], dtype=torch.float32, device=device).unbind(0)

    @classmethod
    def for_scene(cls, scene, selection: str = "uniform", candidates: int = 1,
                  exclude_points: bool = False) -> LightSampler:
        """The sampler of a scene's lights, bounded by its medium's box (``exclude_points``: without the point
        lights, whose direct light equi-angular sampling takes over)."""
        box = scene.grid.box
        lights = tuple(lt for lt in scene.lights if not (exclude_points and isinstance(lt, PointLight)))
        return cls(lights, scene.device, selection, (box.lo, box.hi), candidates)

    def with_lights(self, lights: tuple[Light, ...]) -> LightSampler:
        """The same selection for other lights (an animated sun)."""
        return LightSampler(lights, self.device, self.selection, self.bounds, self.candidates)

    @property
    def entropy_bits(self) -> float:
        """Entropy (bits) of the selection probabilities: ``log2 n`` for ``uniform``, less when the choice
        concentrates on a few lights (0 with one light or none)."""
        return max(0.0, float(-sum(p * math.log2(p) for p in self.pmf if p > 0)))

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
        """Sample one light per point ``x`` ``(N, 3)`` with uniforms ``u`` ``(N, 4)``; requires ``n_lights > 0``.
        The choice (``u[:, 0]``) and the lights' geometry are :class:`LightTable`'s; environment directions come
        from ``u[:, 1:3]`` (uniform sky) or ``u[:, 1:4]`` (a lat-long map)."""
        n = x.shape[0]
        k, inv_select = self.table.choose(self._values, u[:, 0], torch.zeros_like(u[:, 0]))
        # the sample y = (k, omega): an environment light's direction is drawn here, a delta light's direction,
        # distance and contribution at x come from evaluate() (one geometry for sampling and for reuse)
        omega = torch.zeros(n, 3, device=x.device)
        omega[:, 1] = 1.0
        light_pdf = torch.zeros(n, device=x.device)
        is_env = torch.zeros(n, dtype=torch.bool, device=x.device)
        idx = len(self.directional) + len(self.points)
        if self.has_uniform_env:
            m = k == idx
            omega = torch.where(m[:, None], uniform_sphere(u[:, 1:3]), omega)
            is_env = is_env | m
            idx += 1
        # Pdf correction for map samples: use the pdf the sample was drawn with (re-evaluating it from
        # the direction can round into a neighbouring pixel at pixel borders).
        own_fix = torch.zeros(n, device=x.device)
        for emap in self.env_maps:
            m = k == idx
            d, pdf_drawn = emap.sample(u[:, 1:4])
            omega = torch.where(m[:, None], d, omega)
            own_fix = torch.where(m, (pdf_drawn - emap.pdf(d)) * self.pmf[idx], own_fix)
            is_env = is_env | m
            idx += 1
        wi, dist, weight, _ = self.evaluate(k, omega, x)
        inv_select = torch.as_tensor(inv_select, dtype=weight.dtype, device=x.device).expand(n)
        if self.has_env:
            # Environment samples: balance heuristic over all environment lights, i.e. the total
            # environment radiance over the summed pdf (which includes P(select)).
            pdf = self.env_pdf(wi) + own_fix
            light_pdf = torch.where(is_env, pdf, light_pdf)
            weight = torch.where(is_env[:, None], weight / pdf.clamp(min=1e-30)[:, None], weight * inv_select[:, None])
        else:
            weight = weight * inv_select[:, None]
        return LightSample(wi, dist, weight, light_pdf, is_env, k)

    @property
    def env_index(self) -> int:
        """Light index of the first environment light (every environment sample is evaluated as the sum of them
        all, :meth:`evaluate`); ``n_lights`` when there is none."""
        return len(self.directional) + len(self.points) if self.has_env else self.n_lights

    def evaluate(self, light: Tensor, omega: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """A light sample ``y = (light, omega)`` seen from other points: ``(wi (N, 3), distance (N,),
        contribution (N, 3), p_src (N,))`` at points ``x`` ``(N, 3)``.

        ``light`` ``(N,)`` indexes the lights in light order (any environment index, or :attr:`env_index`, means
        the environment direction ``omega``; ``omega`` is ignored for the other lights). ``contribution`` is the
        unshadowed light arriving at ``x`` without the phase function (``irradiance``, ``intensity / r^2``, the
        summed environment radiance); ``p_src`` the source pdf with which :meth:`sample` draws ``y`` (its
        selection probability for a delta light, that times the solid-angle pdf for the environment), the
        same for every ``x``: a sample keeps its meaning when it is reused at another point (ReSTIR, on the
        measure of light index x environment direction)."""
        n, dev = x.shape[0], x.device
        nd, npt = len(self.directional), len(self.points)
        sel = self._pmf[light.clamp(0, max(self.n_lights - 1, 0))] if self.selection != "uniform" else \
            torch.full((n,), 1.0 / max(self.n_lights, 1), device=dev)
        wi, dist, c, _ = self.table.evaluate(self._values, light, tuple(omega.unbind(1)), tuple(x.unbind(1)))
        wi, contribution = torch.stack(wi, 1), torch.stack(c, 1)
        p_src = sel
        if self.has_env:
            env = light >= nd + npt
            contribution = torch.where(env[:, None], self.env_radiance(omega), contribution)
            p_src = torch.where(env, self.env_pdf(omega), sel)
        return wi, dist, contribution, p_src


def power_heuristic(a: Tensor, b: Tensor | float) -> Tensor:
    """Power heuristic ``a^2 / (a^2 + b^2)`` (elementwise), 1 where both are zero."""
    a2, b2 = a * a, b * b
    den = a2 + b2
    return torch.where(den > 0, a2 / den.clamp(min=1e-30), torch.ones_like(den))


def _block(values: list, pos: int, count: int, width: int, like: Tensor) -> Tensor:
    """``values[pos : pos + count x width]`` (numbers or 0-d tensors) as a ``(count, width)`` tensor."""
    vals = values[pos:pos + count * width]
    t = torch.stack(vals) if isinstance(vals[0], Tensor) else torch.tensor(vals, dtype=like.dtype, device=like.device)
    return t.reshape(count, width)


def _pick(m: Tensor, new: tuple, old: tuple) -> tuple:
    """Component-wise ``where(m, new, old)``."""
    return tuple(torch.where(m, n, o) for n, o in zip(new, old))


class LightTable:
    """The one code of the light choice (:meth:`choose`) and the lights' geometry (:meth:`evaluate`), in the form
    a per-slot step consumes; :class:`LightSampler` (eager rows, lat-long maps, the reuse pass's re-evaluation)
    builds on the same two methods. The *structure* (how
    many directional and point lights, whether a uniform sky exists) is fixed, the lights' parameters are
    numbers in :attr:`values` that a compiled step takes as an input, so moving, recolouring or dimming a
    light does not recompile. Lat-long environment maps are not supported (:attr:`supported`).

    Layout of :attr:`values`: per directional light ``-direction (3), irradiance (3)``; per point light
    ``position (3), intensity (3)``; with a uniform sky its radiance ``(3)`` and the NEE pdf of any
    direction, ``P(select sky) / (4 pi)``; with ``power`` or ``ris`` selection (and several lights) then every
    light's selection probability, in light order (the uniform choice needs none). ``ris`` draws
    :attr:`candidates` samples of that source distribution and :func:`~nrc.transport.ris.resample` keeps one
    (:meth:`sample_ris`). The chosen light is looked up by its index in its type's ``(count, 6)`` block (no
    masked selection per light).

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
        self.selection = ("power" if lights.selection == "ris" else lights.selection) if lights.n_lights > 1 \
            else "uniform"
        self.candidates = lights.candidates
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
        """What a compiled step depends on: ``(directional lights, point lights, uniform sky)``, ``"power"``
        for the power (or ``ris`` source) selection of several lights, and ``("ris", M)`` for ``M > 1``
        candidates."""
        base = (self.n_directional, self.n_points, self.has_uniform_env)
        base = (*base, "power") if self.selection == "power" else base
        return (*base, ("ris", self.candidates)) if self.candidates > 1 else base

    @property
    def lanes_per_candidate(self) -> int:
        """Uniforms one :meth:`sample` uses: the light choice (several lights) and a sky direction (2)."""
        return (self.n_lights > 1) + 2 * self.has_uniform_env

    @property
    def lanes(self) -> int:
        """Uniforms :meth:`sample_ris` uses: :attr:`candidates` samples and, for ``M > 1``, the pick."""
        return self.candidates * self.lanes_per_candidate + (self.candidates > 1)

    def sample_ris(self, values: list, x: tuple, u: list, phase_of: Callable[[tuple], Tensor]) -> Candidate:
        """:meth:`sample` for one candidate, :func:`~nrc.transport.ris.resample` over :attr:`candidates` of them
        otherwise (``u``: :attr:`lanes` uniforms; ``phase_of(wi)`` the phase value towards ``wi``)."""
        k = self.lanes_per_candidate
        if self.candidates == 1:
            return self.sample(values, x, u[:k])
        cands = [self.sample(values, x, u[j * k:(j + 1) * k]) for j in range(self.candidates)]
        return resample(cands, phase_of, u[self.candidates * k])[0]

    def choose(self, values: list, u: Tensor, like: Tensor) -> tuple[Tensor, Tensor | int]:
        """``(k, 1 / P(k))``: the chosen light's index in light order (``(N,)`` int64) from the choice's uniform
        ``u`` (unused with one light), with :attr:`values` as numbers or 0-d tensors."""
        n = self.n_lights
        if self.selection == "power":  # the selection probabilities are the last n values: k = CDF steps <= u
            pmf = _block(values, len(values) - n, n, 1, like)[:, 0]
            k = (u[:, None] >= torch.cumsum(pmf, 0)[None, :-1]).long().sum(-1)
            return k, 1.0 / pmf[k].clamp(min=1e-30)
        if n > 1:
            return (u * n).long().clamp(max=n - 1), n
        return torch.zeros_like(like, dtype=torch.long), n

    def evaluate(self, values: list, k: Tensor, omega: tuple, x: tuple) -> tuple[tuple, Tensor, tuple, Tensor]:
        """``(wi, distance, contribution, is_env)`` at points ``x`` of light ``k`` (component form): a delta
        light's direction, distance and unshadowed contribution (``irradiance``, ``intensity / r^2``); for the
        uniform sky the direction ``omega`` and its radiance (``is_env``). Other indices (lat-long maps) keep
        ``wi = omega`` and a zero contribution."""
        zero = torch.zeros_like(x[0])
        wi: tuple = omega
        dist = torch.full_like(zero, math.inf)
        contribution: tuple = (zero, zero, zero)
        is_env = torch.zeros_like(zero, dtype=torch.bool)
        idx, pos = 0, 0
        nd, npt = self.n_directional, self.n_points
        if nd:  # the chosen light's row of the (nd, 6) block
            m = (k >= idx) & (k < idx + nd)
            row = _block(values, pos, nd, 6, zero)[(k - idx).clamp(0, nd - 1)]
            wi = _pick(m, tuple(row[:, j] for j in range(3)), wi)
            contribution = _pick(m, tuple(row[:, j] for j in range(3, 6)), contribution)
            idx, pos = idx + nd, pos + 6 * nd
        if npt:
            m = (k >= idx) & (k < idx + npt)
            row = _block(values, pos, npt, 6, zero)[(k - idx).clamp(0, npt - 1)]
            to = (row[:, 0] - x[0], row[:, 1] - x[1], row[:, 2] - x[2])
            r2 = (to[0] * to[0] + to[1] * to[1] + to[2] * to[2]).clamp(min=1e-12)
            r = torch.sqrt(r2)
            wi = _pick(m, (to[0] / r, to[1] / r, to[2] / r), wi)
            dist = torch.where(m, r, dist)
            contribution = _pick(m, (row[:, 3] / r2, row[:, 4] / r2, row[:, 5] / r2), contribution)
            idx, pos = idx + npt, pos + 6 * npt
        if self.has_uniform_env:
            is_env = k == idx
            contribution = tuple(torch.where(is_env, e + zero, c) for e, c in zip(values[pos:pos + 3], contribution))
        return wi, dist, contribution, is_env

    def sample(self, values: list, x: tuple, u: list) -> tuple[tuple, Tensor, tuple, Tensor, Tensor]:
        """``(wi, distance, weight, light_pdf, is_env)`` as :meth:`LightSampler.sample`, in component form,
        with :attr:`values` as numbers or 0-d tensors and ``u`` the :attr:`lanes` uniforms: :meth:`choose`, the
        sky's direction, :meth:`evaluate`, the weight over the pdf."""
        zero = torch.zeros_like(x[0])
        lane = int(self.n_lights > 1)  # the choice's uniform, then the sky's two
        k, scale = self.choose(values, u[0] if lane else zero, zero)
        omega: tuple = (zero, zero + 1.0, zero)
        if self.has_uniform_env:
            sky = k == self.n_directional + self.n_points
            omega = _pick(sky, sphere_direction(u[lane], u[lane + 1]), omega)
        wi, dist, contribution, is_env = self.evaluate(values, k, omega, x)
        if self.has_uniform_env:
            pdf = values[6 * (self.n_directional + self.n_points) + 3]
            light_pdf = torch.where(is_env, zero + pdf, zero)
            weight = tuple(torch.where(is_env, c / pdf, c * scale) for c in contribution)
        else:
            light_pdf = zero
            weight = tuple(c * scale for c in contribution)
        return wi, dist, weight, light_pdf, is_env
