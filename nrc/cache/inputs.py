"""Raw network inputs of the radiance cache, built identically for training and for queries.

For a world position ``x`` and a unit direction ``d`` the raw input row is the concatenation of

1. the position normalised to the medium's box, ``grid.box.normalize(x)`` clamped to ``[0, 1]^3``;
2. the direction, either as the unit vector ``d`` (3 columns, in ``[-1, 1]``) or as spherical angles
   (2 columns in ``[0, 1]``) with world ``+y`` (up) as the pole, the same convention as the
   lat-long environment map of SCENE.md:
   ``theta / pi = acos(d.y) / pi`` and ``phi / 2pi = atan2(d.x, -d.z) / 2pi`` wrapped to ``[0, 1)``
   so that ``phi`` and ``phi + 2 pi`` agree (the azimuth column is periodic);
3. the selected extra inputs read from the density grid at ``x``: the normalised density
   (``[0, 1]``, 1 column), its normalised gradient (``[-1, 1]^3``, 3 columns) and its normalised
   Laplacian (``[-1, 1]``, 1 column), in that order; all zero outside the box;
4. with ``light_depth``, the optical depth ``tau`` from ``x`` towards the scene's key light (:func:`key_light`: the
   directional or point light that sends the most power into the medium), as ``log(1 + tau) / log(1 + tau_ref)``
   clamped to ``[0, 1]`` (1 column; ``tau_ref``: :func:`nrc.volume.optical_depth.axis_chord_depth`, a constant of
   the medium), read trilinearly from a coarse field (:func:`nrc.volume.optical_depth.light_optical_depth_field`,
   ``light_depth_resolution`` cells along the longest axis) computed when the cache is built and again whenever
   the key light moves (:meth:`InputBuilder.set_lights`). It tells the cache where the medium shadows its light,
   which the hash grid otherwise learns from scratch (``docs/measurements/learning.md``, "The optical depth to the
   light as an input").

The same :class:`InputBuilder` serves :meth:`RadianceCache.train_step` and :meth:`RadianceCache.query`,
so the extras can never differ between training and inference.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from nrc.config import ConfigReader
from nrc.transport.light_sampling import light_powers
from nrc.transport.lights import DirectionalLight, Light, PointLight
from nrc.volume.box import Box
from nrc.volume.grid import CellField, DensityGrid
from nrc.volume.optical_depth import axis_chord_depth, light_optical_depth_field

DirectionMode = Literal["vector", "spherical"]


@dataclass(frozen=True)
class ExtraInputs:
    """Which density-grid features are appended to the network input (config group ``extra_inputs``).

    Config keys: ``density``, ``gradient``, ``laplacian``, ``light_depth`` (booleans), ``light_depth_resolution``,
    ``light_depth_bins``.
    """

    density: bool = False
    """The normalised density ``D(x) / max D`` (1 column, un-encoded)."""
    gradient: bool = False
    """Its normalised gradient (3 columns, un-encoded)."""
    laplacian: bool = False
    """Its normalised Laplacian (1 column, un-encoded)."""
    light_depth: bool = False
    """The log-scaled optical depth towards the key light (1 column; nothing in a scene without a directional or
    point light)."""
    light_depth_resolution: int | None = None
    """Cells of the light-depth field along the grid's longest axis (>= 2); None (``auto``):
    :func:`light_depth_cells`."""
    light_depth_bins: int = 16
    """One-blob bins of the light-depth column (0: un-encoded)."""

    @property
    def n_dims(self) -> int:
        """Columns of the density block (density, gradient, Laplacian); the light depth is a block of its own."""
        return int(self.density) + 3 * int(self.gradient) + int(self.laplacian)

    @classmethod
    def from_config(cls, cfg: ConfigReader) -> ExtraInputs:
        extras = cls(
            density=cfg.get_bool("density", False), gradient=cfg.get_bool("gradient", False),
            laplacian=cfg.get_bool("laplacian", False), light_depth=cfg.get_bool("light_depth", False),
            light_depth_resolution=cfg.get_int_or_auto("light_depth_resolution", "auto", lo=2),
            light_depth_bins=cfg.get_int("light_depth_bins", 16, lo=0),
        )
        cfg.finish()
        return extras


LIGHT_DEPTH_CELLS = {"static": 64, "animated": 32}
"""``light_depth_resolution: auto``: the field's cells along the longest axis. Under ``renderer.animate`` the field is
recomputed whenever the sun turns (every frame): 32 cells cost ~0.09 s on one thread against ~0.44 s for 64
(the Disney cloud; ``docs/measurements/learning.md``)."""


def light_depth_cells(extras: ExtraInputs, animated: bool) -> int:
    """The light-depth field's resolution: the key's, or :data:`LIGHT_DEPTH_CELLS` by whether the camera or a
    light moves."""
    if extras.light_depth_resolution is not None:
        return extras.light_depth_resolution
    return LIGHT_DEPTH_CELLS["animated" if animated else "static"]


def key_light(lights: Sequence[Light], box: Box) -> DirectionalLight | PointLight | None:
    """The directional or point light that sends the most power into the medium's bounding sphere (the light
    sampler's :func:`~nrc.transport.light_sampling.light_powers`; the first of equals, directional lights first), or
    None."""
    deltas = tuple([lt for lt in lights if isinstance(lt, DirectionalLight)]
                   + [lt for lt in lights if isinstance(lt, PointLight)])
    if not deltas:
        return None
    powers = light_powers(deltas, box.center, float(torch.linalg.vector_norm(box.extent)) / 2)
    return deltas[max(range(len(deltas)), key=powers.__getitem__)]


def spherical_coordinates(d: Tensor) -> Tensor:
    """``(N, 2)`` = ``(theta / pi, phi / 2pi)`` of directions ``(N, 3)`` (need not be unit), both in ``[0, 1]``
    and the azimuth in ``[0, 1)``; pole ``+y``, azimuth 0 towards ``-z``, a quarter turn towards ``+x``."""
    x, y, z = d.unbind(-1)
    theta = torch.atan2(torch.hypot(x, z), y) / math.pi
    phi = torch.atan2(x, -z) / (2.0 * math.pi)
    phi = phi - phi.floor()
    phi = torch.where(phi >= 1.0, torch.zeros_like(phi), phi)  # -tiny wraps to 1.0 in float32
    return torch.stack((theta, phi), dim=-1)


class InputBuilder:
    """Builds raw network inputs ``(N, n_dims)`` float32 from world positions, directions and the grid.

    Args:
        grid: the medium's density grid (box for normalisation, source of the extras).
        direction_mode: ``"vector"`` (unit vector, 3 columns) or ``"spherical"`` (2 columns, azimuth periodic).
        extras: the extra inputs to append.
        lights: the scene's lights (for ``light_depth``: its key light; none: no light-depth column).
        animated: whether the camera or a light moves (``light_depth_resolution: auto``).

    Attributes:
        column_blocks: ``(n_dims, periodic flags)`` of the position, direction and (if any) density-extras and
            light-depth blocks, in column order.
        light_field: the light-depth field's sampler (None without a light-depth column).
    """

    def __init__(self, grid: DensityGrid, direction_mode: DirectionMode, extras: ExtraInputs,
                 lights: Sequence[Light] = (), animated: bool = False) -> None:
        self.grid = grid
        self.direction_mode = direction_mode
        self.extras = extras
        direction_periodic = (False, True) if direction_mode == "spherical" else (False, False, False)
        blocks = [(3, (False,) * 3), (len(direction_periodic), direction_periodic)]
        if extras.n_dims:
            blocks.append((extras.n_dims, (False,) * extras.n_dims))
        self.light_field: CellField | None = None
        self._key: tuple[float, ...] | None = None
        self._light_column = extras.light_depth and key_light(lights, grid.box) is not None
        self._cells = light_depth_cells(extras, animated)
        self._keep = not animated  # a static light's field is kept on disk; a moving light's changes every frame
        if self._light_column:
            self._log_ref = math.log1p(max(axis_chord_depth(grid), 1e-6))
            self.set_lights(lights)
            blocks.append((1, (False,)))
        self.column_blocks = tuple(blocks)
        self.n_dims = sum(n for n, _ in blocks)

    def set_lights(self, lights: Sequence[Light]) -> bool:
        """Recompute the light-depth field if the key light moved (``renderer.animate``); returns whether it did.
        The field's tensor is updated in place (a captured graph that reads it stays valid)."""
        if not self._light_column:
            return False
        light = key_light(lights, self.grid.box)
        if light is None:
            return False
        directional = isinstance(light, DirectionalLight)
        vec = light.direction if directional else light.position
        key = (float(directional), *(float(v) for v in vec))
        if key == self._key:
            return False
        tau = light_optical_depth_field(self.grid, resolution=self._cells, keep=self._keep,
                                        **{"direction" if directional else "position": vec})
        value = (torch.log1p(tau) / self._log_ref).clamp(0.0, 1.0)
        if self.light_field is None:
            self.light_field = CellField(value)
        else:
            self.light_field.assign(value)
        self._key = key
        return True

    def __call__(self, positions: Tensor, directions: Tensor) -> Tensor:
        """Raw inputs for world ``positions`` ``(N, 3)`` and ``directions`` ``(N, 3)`` -> ``(N, n_dims)``
        (on the grid's device)."""
        positions = positions.to(self.grid.device, torch.float32)
        directions = directions.to(self.grid.device, torch.float32)
        cols = [self.grid.box.normalize(positions).clamp(0.0, 1.0)]
        if self.direction_mode == "spherical":
            cols.append(spherical_coordinates(directions))
        else:
            cols.append(directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12))
        if self.extras.density:
            cols.append(self.grid.normalized_density(positions)[:, None])
        if self.extras.gradient:
            cols.append(self.grid.gradient(positions))
        if self.extras.laplacian:
            cols.append(self.grid.laplacian(positions)[:, None])
        if self.light_field is not None:
            cols.append(self.light_field(self.grid.box.normalize(positions).clamp(0.0, 1.0))[:, None])
        return torch.cat(cols, dim=1)
