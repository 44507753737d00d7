"""Light sources of a scene (SCENE.md conventions).

* :class:`DirectionalLight`: parallel light propagating along ``direction`` (unit); at a point ``x`` it
  contributes ``irradiance * p(cos) * T(x -> box exit along -direction)``.
* :class:`PointLight`: isotropic point at ``position``; contributes ``intensity / r^2 * p(cos) * T``.
* :class:`EnvironmentLight`: radiance arriving from every direction at infinity, either uniform
  (``radiance``) or a lat-long image, times ``scale``. A unit direction ``d`` pointing away from the scene
  maps to ``u = atan2(d.x, -d.z) / 2pi`` (wrapped to [0, 1), column 0 faces -z, a quarter turn faces +x)
  and ``v = acos(d.y) / pi`` (row 0 straight up), with bilinear lookup.

All vectors are float32 tensors on the scene's device; RGB values are linear, their luminance Rec. 709
(:data:`LUMINANCE`, :func:`luminance3`).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

LUMINANCE = (0.2126, 0.7152, 0.0722)


@dataclass(frozen=True)
class DirectionalLight:
    direction: Tensor  # (3,) unit propagation direction (from the light towards the scene)
    irradiance: Tensor  # (3,) RGB irradiance on a plane perpendicular to the direction


@dataclass(frozen=True)
class PointLight:
    position: Tensor  # (3,) world position
    intensity: Tensor  # (3,) RGB radiant intensity (power per solid angle)


@dataclass(frozen=True)
class EnvironmentLight:
    radiance: Tensor | None  # (3,) uniform RGB radiance, or None when `image` is given
    image: Tensor | None  # (H, W, 3) lat-long RGB radiance, or None for a uniform sky
    scale: float = 1.0


Light = DirectionalLight | PointLight | EnvironmentLight


def luminance3(c: tuple) -> Tensor:
    """Rec. 709 luminance of an RGB triple in component form."""
    return LUMINANCE[0] * c[0] + LUMINANCE[1] * c[1] + LUMINANCE[2] * c[2]
