"""Mitsuba 3 bridge: render a :class:`~nrc.scene.Scene` with an independent renderer (SCENE.md contract).

Mitsuba 3 (``pip install mitsuba==3.9.1``, the ``validate`` extra) is optional: importing this module never
imports Mitsuba; :func:`mitsuba_available` tells whether it can be used.

Conventions converted (each checked numerically, see ``tests/test_mitsuba_bridge.py``):

* **Integrator** -- ``volpath`` with ``max_depth = max_scatter + 1``: Mitsuba increments the depth at each
  real scattering event and gathers light (emitter sampling, and emitters hit by the phase-sampled ray) only
  while ``depth < max_depth``; null-BSDF crossings of the medium's box do not count. ``rr_depth = max_depth``
  disables Russian roulette (it only acts when ``depth > rr_depth``). Emitters stay visible to camera rays.
* **Camera** -- ``perspective`` with ``fov_axis = "y"`` and a ``look_at`` frame built from the camera's
  position, ``position + forward`` and ``up``. Mitsuba's camera space has +x to the *left*, and its film x
  runs along camera -x, so image +x is world ``normalize(cross(forward, up))`` and row 0 is the top: no
  extra flip is needed (checked pixel by pixel against :meth:`Camera.generate_rays`). Box reconstruction
  filter (radius 0.5: each sample lands in the pixel it was drawn in, uniformly), ``independent`` sampler.
* **Density grid** -- ``gridvolume`` data is indexed ``data[z][y][x]``, so ``D`` ``(nx, ny, nz)`` is passed
  transposed to ``(nz, ny, nx, 1)``. Its lookups (a Dr.Jit ``Texture3f``, ``wrap_mode = clamp``) are
  cell-centred and trilinear with clamping inside half a cell of the faces, as ours; the volume's
  ``to_world`` maps ``[0, 1]^3`` onto our box (no half-cell offset). It agrees with
  :meth:`DensityGrid.lookup` to float precision inside the box. Outside the box the density is zero
  because the medium lives inside a ``cube`` shape with a ``null`` BSDF scaled onto the same box.
* **Medium** -- ``heterogeneous`` with ``sigma_t = gridvolume`` and ``scale = density_scale``, constant
  ``albedo``, ``hg`` phase with our ``g`` (Mitsuba's ``g > 0`` is forward scattering, as ours).
* **Lights** -- ``directional``: Mitsuba's ``direction`` is the propagation direction, as ours (its
  emitter sample points towards ``-direction``); ``irradiance`` as is. ``point``: ``intensity`` (weight
  ``intensity / r^2``). A uniform environment is a ``constant`` emitter with ``radiance * scale``.
  A lat-long image is an ``envmap``: Mitsuba maps a direction ``d`` to ``u = atan2(d.x, -d.z) / 2pi``,
  ``v = acos(d.y) / pi`` exactly as SCENE.md does, so its ``to_world`` is the identity. Texel placement
  differs vertically: we read the image with texel centres at ``((i + 0.5) / W, (j + 0.5) / H)``
  (:func:`latlong_lookup`: wrapping in u, clamping to the first/last row's centre in v), while Mitsuba puts
  column centres at ``(i + 0.5) / W`` (same) but rows at ``v = j / (H - 1)``. The image handed to Mitsuba
  therefore has ``2H + 1`` rows: the poles (copies of rows 0 and H-1), the original rows, and the midpoints
  between neighbouring rows; bilinear interpolation on that grid reproduces ours exactly.
  Several environment lights are merged into one emitter (Mitsuba allows one).
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from nrc.scene import Scene

DEFAULT_VARIANT = "scalar_rgb"

__all__ = [
    "DEFAULT_VARIANT",
    "mitsuba_available",
    "to_mitsuba_dict",
    "render_mitsuba",
    "latlong_lookup",
    "latlong_rows_for_mitsuba",
]


def mitsuba_available() -> bool:
    """True when Mitsuba 3 can be imported (the project works without it)."""
    try:
        import mitsuba  # noqa: F401
    except Exception:  # ImportError, or a broken native install
        return False
    return True


def _mitsuba(variant: str):
    """Import Mitsuba and switch it to ``variant`` (a process-wide setting)."""
    try:
        import mitsuba as mi
    except Exception as exc:  # pragma: no cover - exercised only without Mitsuba
        raise RuntimeError("Mitsuba 3 is not installed: pip install mitsuba==3.9.1 (the 'validate' extra)") from exc
    if not variant.endswith("_rgb"):
        raise ValueError(f"Mitsuba bridge: an RGB variant is needed (scalar_rgb, llvm_ad_rgb), got {variant!r}")
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


def _vec(t: Any) -> list[float]:
    return [float(v) for v in (t.detach().cpu().tolist() if hasattr(t, "detach") else list(t))]


# ---------------------------------------------------------------------------- environment images
def latlong_lookup(image: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lat-long lookup as the bridge interprets SCENE.md (reference for tests).

    ``d`` ``(N, 3)`` unit directions pointing away from the scene map to ``u = atan2(d.x, -d.z) / 2pi``
    (wrapped to [0, 1)) and ``v = acos(d.y) / pi``. Texel ``(row j, column i)`` of an ``(H, W, C)`` image is
    centred at ``((i + 0.5) / W, (j + 0.5) / H)``; u wraps around, v clamps to the first/last row's centre.
    """
    image = np.asarray(image, dtype=np.float64)
    h, w = image.shape[:2]
    d = np.asarray(d, dtype=np.float64)
    u = np.mod(np.arctan2(d[:, 0], -d[:, 2]) / (2.0 * math.pi), 1.0)
    v = np.arccos(np.clip(d[:, 1], -1.0, 1.0)) / math.pi
    x = u * w - 0.5
    y = np.clip(v * h - 0.5, 0.0, h - 1.0)
    x0 = np.floor(x)
    fx = (x - x0)[:, None]
    x0 = x0.astype(np.int64) % w
    x1 = (x0 + 1) % w
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    fy = (y - y0)[:, None]
    y1 = np.minimum(y0 + 1, h - 1)
    return (
        image[y0, x0] * (1 - fx) * (1 - fy) + image[y0, x1] * fx * (1 - fy)
        + image[y1, x0] * (1 - fx) * fy + image[y1, x1] * fx * fy
    )


def latlong_rows_for_mitsuba(image: np.ndarray) -> np.ndarray:
    """Resample an ``(H, W, C)`` lat-long image to the ``(2H + 1, W, C)`` one that Mitsuba's ``envmap``
    (rows at ``v = j / (rows - 1)``) interpolates exactly as :func:`latlong_lookup` reads ``image``."""
    image = np.asarray(image, dtype=np.float32)
    h = image.shape[0]
    out = np.empty((2 * h + 1,) + image.shape[1:], dtype=np.float32)
    out[0] = image[0]
    out[-1] = image[-1]
    out[1:-1:2] = image
    out[2:-1:2] = 0.5 * (image[:-1] + image[1:])
    return np.ascontiguousarray(out)


# ---------------------------------------------------------------------------- scene dict
def _rgb(values: list[float]) -> dict:
    return {"type": "rgb", "value": [float(v) for v in values]}


def _environment(mi, lights: list) -> dict | None:
    """One Mitsuba environment emitter for all our environment lights (``None`` if there are none)."""
    if not lights:
        return None
    uniform = np.zeros(3, dtype=np.float64)
    images = []
    for light in lights:
        if light.image is None:
            uniform += np.asarray(_vec(light.radiance)) * light.scale
        else:
            images.append(light.image.detach().cpu().numpy().astype(np.float32) * np.float32(light.scale))
    if not images:
        return {"type": "constant", "radiance": _rgb(list(uniform))}
    if len(images) > 1:
        if any(im.shape != images[0].shape for im in images[1:]):
            raise NotImplementedError("Mitsuba bridge: several environment images of different sizes")
    image = np.sum(images, axis=0) + uniform.astype(np.float32)
    return {"type": "envmap", "bitmap": mi.Bitmap(latlong_rows_for_mitsuba(image)), "scale": 1.0}


def to_mitsuba_dict(scene: Scene, spp: int | None = None, variant: str = DEFAULT_VARIANT) -> dict:
    """The Mitsuba 3 scene dict (for ``mi.load_dict``) reproducing ``scene`` under the SCENE.md contract.

    Sets Mitsuba's process-wide variant to ``variant`` (the dict holds variant-specific objects).
    ``spp`` defaults to ``scene.integrator.spp``; the sampler's seed is ``scene.integrator.seed``.
    """
    from nrc.transport.lights import DirectionalLight, EnvironmentLight, PointLight

    mi = _mitsuba(variant)
    T = mi.ScalarTransform4f
    grid, cam, integ = scene.grid, scene.camera, scene.integrator
    spp = int(integ.spp if spp is None else spp)
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")

    lo = np.asarray(_vec(grid.box.lo), dtype=np.float64)
    hi = np.asarray(_vec(grid.box.hi), dtype=np.float64)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    density = grid.density.detach().cpu().numpy().astype(np.float32)
    zyx = np.ascontiguousarray(density.transpose(2, 1, 0))[..., None]  # Mitsuba indexes data[z][y][x]
    medium = {
        "type": "heterogeneous",
        "sigma_t": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(zyx),
            "filter_type": "trilinear",
            "wrap_mode": "clamp",
            "to_world": T().translate(mi.ScalarPoint3f(*lo)).scale(mi.ScalarPoint3f(*(hi - lo))),
        },
        "scale": float(grid.density_scale),
        "albedo": float(scene.albedo),
        "phase": {"type": "hg", "g": float(scene.g)},
    }

    position = np.asarray(_vec(cam.position), dtype=np.float64)
    forward = np.asarray(_vec(cam.forward), dtype=np.float64)
    up = np.asarray(_vec(cam.up), dtype=np.float64)
    far = float(np.linalg.norm(np.abs(position - centre) + half))  # farthest box corner
    scale = max(far, float(np.linalg.norm(hi - lo)), 1e-6)
    camera_inside = bool(np.all(position > lo) and np.all(position < hi))
    sensor = {
        "type": "perspective",
        "fov_axis": "y",
        "fov": float(cam.fov_y),
        "near_clip": 1e-5 * scale,
        "far_clip": 1e3 * scale,
        "to_world": T().look_at(
            origin=mi.ScalarPoint3f(*position),
            target=mi.ScalarPoint3f(*(position + forward)),
            up=mi.ScalarVector3f(*up),
        ),
        "film": {
            "type": "hdrfilm",
            "width": int(cam.width),
            "height": int(cam.height),
            "pixel_format": "rgb",
            "component_format": "float32",
            "rfilter": {"type": "box"},
        },
        "sampler": {"type": "independent", "sample_count": spp, "seed": int(integ.seed)},
    }
    if camera_inside:
        sensor["medium"] = {"type": "ref", "id": "cloud"}

    max_depth = int(integ.max_scatter) + 1
    out: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": max_depth, "rr_depth": max_depth + 1, "hide_emitters": False},
        "cloud": medium,
        "sensor": sensor,
        "box": {
            "type": "cube",
            "to_world": T().translate(mi.ScalarPoint3f(*centre)).scale(mi.ScalarPoint3f(*half)),
            "bsdf": {"type": "null"},
            "interior": {"type": "ref", "id": "cloud"},
        },
    }
    for n, light in enumerate(scene.lights_of(DirectionalLight)):
        out[f"sun_{n}"] = {
            "type": "directional",
            "direction": mi.ScalarVector3f(*_vec(light.direction)),  # propagation direction, as ours
            "irradiance": _rgb(_vec(light.irradiance)),
        }
    for n, light in enumerate(scene.lights_of(PointLight)):
        out[f"point_{n}"] = {
            "type": "point",
            "position": mi.ScalarPoint3f(*_vec(light.position)),
            "intensity": _rgb(_vec(light.intensity)),
        }
    env = _environment(mi, scene.lights_of(EnvironmentLight))
    if env is not None:
        out["environment"] = env
    return out


# ---------------------------------------------------------------------------- rendering
def render_mitsuba(
    scene: Scene,
    spp: int | None = None,
    seed: int = 0,
    variant: str = DEFAULT_VARIANT,
    threads: int | None = None,
) -> tuple[np.ndarray, float]:
    """Render ``scene`` with Mitsuba 3.

    Args:
        scene: the scene to render.
        spp: samples per pixel (default ``scene.integrator.spp``).
        seed: Mitsuba's sampler seed for this render (it overrides the dict's ``scene.integrator.seed``).
        variant: Mitsuba variant (``scalar_rgb``, or ``llvm_ad_rgb`` where LLVM is installed).
        threads: worker threads (default: Dr.Jit's current setting, one per core).

    Returns:
        ``(image, seconds)``: the linear RGB image ``(H, W, 3)`` float32 with row 0 at the top, and the
        wall-clock render time (excluding building and loading the scene; for JIT variants it includes
        kernel compilation unless cached).
    """
    mi = _mitsuba(variant)
    import drjit as dr

    if threads is not None:
        dr.set_thread_count(int(threads))
    mscene = mi.load_dict(to_mitsuba_dict(scene, spp=spp, variant=variant))
    start = time.perf_counter()
    img = mi.render(mscene, seed=int(seed), spp=int(scene.integrator.spp if spp is None else spp))
    image = np.array(img, dtype=np.float32)  # forces evaluation on JIT variants
    seconds = time.perf_counter() - start
    return np.ascontiguousarray(image[..., :3]), seconds
