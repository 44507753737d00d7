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
   Laplacian (``[-1, 1]``, 1 column), in that order; all zero outside the box.

The same :class:`InputBuilder` serves :meth:`RadianceCache.train_step` and :meth:`RadianceCache.query`,
so the extras can never differ between training and inference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from nrc.config import ConfigReader
from nrc.volume.grid import DensityGrid

DirectionMode = Literal["vector", "spherical"]


@dataclass(frozen=True)
class ExtraInputs:
    """Which density-grid features are appended to the network input (config group ``extra_inputs``).

    Config keys (booleans): ``density``, ``gradient``, ``laplacian``.
    """

    density: bool = False
    gradient: bool = False
    laplacian: bool = False

    @property
    def n_dims(self) -> int:
        return int(self.density) + 3 * int(self.gradient) + int(self.laplacian)

    @classmethod
    def from_config(cls, cfg: ConfigReader) -> ExtraInputs:
        extras = cls(
            density=cfg.get_bool("density", False), gradient=cfg.get_bool("gradient", False),
            laplacian=cfg.get_bool("laplacian", False),
        )
        cfg.finish()
        return extras


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

    Attributes:
        column_blocks: ``(n_dims, periodic flags)`` of the position, direction and (if any) extras blocks.
    """

    def __init__(self, grid: DensityGrid, direction_mode: DirectionMode, extras: ExtraInputs) -> None:
        self.grid = grid
        self.direction_mode = direction_mode
        self.extras = extras
        direction_periodic = (False, True) if direction_mode == "spherical" else (False, False, False)
        blocks = [(3, (False,) * 3), (len(direction_periodic), direction_periodic)]
        if extras.n_dims:
            blocks.append((extras.n_dims, (False,) * extras.n_dims))
        self.column_blocks = tuple(blocks)
        self.n_dims = sum(n for n, _ in blocks)

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
        return torch.cat(cols, dim=1)
