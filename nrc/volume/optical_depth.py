"""Optical depth of a scene along its camera rays: how thick the medium is where the camera sees it.

``tau = integral of sigma_t(x) dx`` along a pixel's centre ray, from where it enters the grid's box to where it
leaves (the whole chord, not just to the first scattering event). Over the pixels whose ray meets the medium
(``tau > 0``) the median ``tau`` says which regime a scene is in: a moderate cloud has a median of a few, a real
cumulus 50-100 (there a camera sample scatters dozens to hundreds of times). ``tau (1 - g)`` is the reduced
(transport) optical depth: under strong forward scattering (``g`` near 1) light goes deeper per scattering event,
so the number of events grows roughly with ``(tau (1 - g))^2`` for a thick slab.

The integral is the midpoint rule with ``steps_per_voxel`` steps per voxel edge along the ray (trilinear density:
exact to the rule's error, which the tests bound on a hand-made grid). Memory: ``chunk`` rays and one lookup each
per step at a time; the loop runs over steps, never over rays.

:func:`light_optical_depth_field` is the same integral from the cells of a coarse grid over the box towards a light
(the radiance cache's ``extra_inputs.light_depth``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.io.disk_cache import cached_array
from nrc.volume import box as _box_module
from nrc.volume import grid as _grid_module


def centre_ray_chords(camera: Any, grid: Any, chunk: int = 1 << 14) -> Iterator[tuple[Tensor, ...]]:
    """``(pix, o, d, t0, t1)`` per chunk of ``chunk`` pixels: the pixels (flat indices) whose centre ray crosses the
    grid's box, their rays and the box's entry / exit distances (``t0`` may be negative: the camera inside the
    box). Chunks without such a pixel are skipped. The one walk over the camera's centre rays that the optical depth
    and the NRC training budget's medium mask (``training_set.medium_pixel_mask``) share."""
    dev = grid.device
    n = camera.num_pixels
    for start in range(0, n, chunk):
        pix = torch.arange(start, min(n, start + chunk), device=dev)
        o, d = camera.generate_rays(pix, torch.full((len(pix), 2), 0.5, device=dev))
        t0, t1 = grid.box.intersect(o, d)
        hit = t1 > t0
        if bool(hit.any()):
            yield pix[hit], o[hit], d[hit], t0[hit], t1[hit]


def camera_optical_depths(camera: Any, grid: Any, steps_per_voxel: float = 2.0, chunk: int = 1 << 14) -> Tensor:
    """``(H * W,)`` float32 optical depth of every pixel's centre ray through ``grid`` (0 where it misses).

    Args:
        camera: a :class:`nrc.camera.Camera` (``num_pixels``, ``generate_rays``).
        grid: a :class:`nrc.volume.grid.DensityGrid` (its ``sigma_t`` includes the density scale).
        steps_per_voxel: midpoint-rule steps per voxel edge of path length (> 0).
    """
    if not steps_per_voxel > 0:
        raise ValueError(f"steps_per_voxel must be > 0, got {steps_per_voxel}")
    out = torch.zeros(camera.num_pixels, dtype=torch.float32, device=grid.device)
    dt_max = grid.voxel_size / steps_per_voxel
    for pix, o, d, t0, t1 in centre_ray_chords(camera, grid, chunk):
        t0 = t0.clamp(min=0.0)  # from the camera on
        ahead = t1 > t0
        if not bool(ahead.any()):
            continue
        pix, o, d, t0, t1 = pix[ahead], o[ahead], d[ahead], t0[ahead], t1[ahead]
        out[pix] = _midpoint_depth(grid, o, d, t0, t1, dt_max)
    return out


def _midpoint_depth(grid: Any, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor, dt_max: float) -> Tensor:
    """``(N,)`` optical depth of the segments ``o + t d``, ``t`` in ``[t0, t1]``, by the midpoint rule: every segment
    gets the same number of midpoints (the longest's ``length / dt_max``, rounded up), each its own step."""
    length = t1 - t0
    steps = max(1, math.ceil(float(length.max()) / dt_max))
    dt = length / steps  # each ray's own step: exactly `steps` midpoints over its chord
    tau = torch.zeros_like(length)
    for i in range(steps):
        x = o + (t0 + (i + 0.5) * dt)[:, None] * d
        tau += grid.sigma_t(x) * dt
    return tau


@dataclass(frozen=True)
class OpticalDepth:
    """Optical depth over the camera rays that meet the medium (``docs/scenes.md`` lists it per preset)."""

    median: float
    """Median ``tau`` over the pixels whose centre ray meets the medium."""
    p10: float
    """10th percentile of those ``tau``."""
    p90: float
    """90th percentile."""
    median_reduced: float
    """Median of ``tau (1 - g)`` (the transport optical depth)."""
    medium_pixels: int
    """Pixels whose centre ray meets the medium (``tau > 0``)."""
    pixels: int
    """All pixels."""


def scene_optical_depth(scene: Any, steps_per_voxel: float = 2.0) -> OpticalDepth:
    """:class:`OpticalDepth` of a loaded :class:`nrc.scene.Scene` over its camera's pixel centres."""
    tau = camera_optical_depths(scene.camera, scene.grid, steps_per_voxel).double()
    seen = tau[tau > 0]
    if seen.numel() == 0:
        return OpticalDepth(0.0, 0.0, 0.0, 0.0, 0, int(tau.numel()))
    q = torch.quantile(seen, torch.tensor([0.1, 0.5, 0.9], dtype=seen.dtype, device=seen.device)).tolist()
    return OpticalDepth(median=q[1], p10=q[0], p90=q[2], median_reduced=q[1] * (1.0 - float(scene.g)),
                        medium_pixels=int(seen.numel()), pixels=int(tau.numel()))


def axis_chord_depth(grid: Any) -> float:
    """The largest optical depth of a chord through the grid along one of its axes (cell sums times the voxel edge):
    a constant of the medium that the light-depth input is scaled by, whatever the light's direction."""
    sums = [float(grid.density.sum(a).max()) for a in range(3)]
    return max(sums) * grid.density_scale * grid.voxel_size


LIGHT_FIELD_SOURCES = (__file__, _grid_module.__file__, _box_module.__file__)  # the code a kept field is made by


def light_optical_depth_field(grid: Any, direction: Tensor | None = None, position: Tensor | None = None,
                              resolution: int = 64, steps_per_voxel: float = 0.5, chunk: int = 1 << 16,
                              keep: bool = False) -> Tensor:
    """Optical depth from the centre of every cell of a coarse grid over the box towards a light: along ``-direction``
    to the box's exit (a directional light propagating along ``direction``), or towards ``position`` up to the light
    or the box's exit, whichever is nearer (a point light). Exactly one of the two is given.

    Args:
        grid: a :class:`nrc.volume.grid.DensityGrid`.
        direction, position: ``(3,)``, the light's propagation direction (need not be unit) or world position.
        resolution: cells along the grid's longest axis (the others in proportion, at least 1); never more than the
            density grid has there (a finer field than the medium's own cells only costs: ``64^3`` cells over a
            test's ``24^3`` grid marched 20x the rays).
        steps_per_voxel: midpoint-rule steps per voxel edge of the density grid (> 0; 0.5: a step of two voxels).
        chunk: cells marched at a time.
        keep: keep the field on disk (:func:`nrc.io.disk_cache.cached_array`, keyed by the grid's
            :meth:`~nrc.volume.grid.DensityGrid.fingerprint`, the light and these arguments): a later run on the same
            medium and light reads it instead of marching again (seconds on the Disney cloud; the same values).

    Returns:
        ``(rx, ry, rz)`` float32 on the grid's device, cell-centred like the grid (sample it with
        :class:`nrc.volume.grid.CellField`). Memory: ``chunk`` cells and one lookup each per step.
    """
    if (direction is None) == (position is None):
        raise ValueError("light_optical_depth_field: give exactly one of direction and position")
    if not (resolution >= 1 and steps_per_voxel > 0):
        raise ValueError(f"resolution must be >= 1 and steps_per_voxel > 0, got {resolution}, {steps_per_voxel}")
    resolution = min(resolution, max(grid.shape))
    if keep:
        light = (direction if direction is not None else position).detach().cpu().double().tolist()
        params = (grid.fingerprint(), direction is not None, tuple(light), resolution, steps_per_voxel, chunk,
                  grid.device.type)
        field = cached_array("light_depth", params, LIGHT_FIELD_SOURCES, lambda: light_optical_depth_field(
            grid, direction, position, resolution, steps_per_voxel, chunk).cpu().numpy())
        return torch.from_numpy(field).to(grid.device)
    dev = grid.device
    shape = [max(1, round(n * resolution / max(grid.shape))) for n in grid.shape]
    axes = [(torch.arange(n, device=dev, dtype=torch.float32) + 0.5) / n for n in shape]
    s = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    x = grid.box.lo + s * (grid.box.hi - grid.box.lo)
    out = torch.zeros(len(x), dtype=torch.float32, device=dev)
    dt_max = grid.voxel_size / steps_per_voxel
    for a in range(0, len(x), chunk):
        xo = x[a:a + chunk]
        if direction is not None:
            d = (-direction / direction.norm()).to(dev, torch.float32).expand_as(xo)
        else:
            to = position.to(dev, torch.float32) - xo
            d = to / to.norm(dim=-1).clamp_min(1e-12)[:, None]
        _, t1 = grid.box.intersect(xo, d)
        if position is not None:  # up to the light, if it is inside the box
            t1 = torch.minimum(t1, to.norm(dim=-1))
        out[a:a + chunk] = _midpoint_depth(grid, xo, d, torch.zeros_like(t1), t1, dt_max)
    return out.reshape(shape)
