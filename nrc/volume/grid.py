"""Dense density grid placed in a world box, with batched trilinear lookups (SCENE.md conventions).

Conventions (binding, from ``SCENE.md``):

* ``D[i, j, k]`` has shape ``(nx, ny, nz)``; ``i`` runs along world +x, ``j`` along +y, ``k`` along +z.
* The box is centred at ``center`` with diagonal length ``diagonal``; cells are cubic with edge
  ``voxel_size = diagonal / |(nx, ny, nz)|``, so the box keeps the grid's aspect.
* ``D[i, j, k]`` is the value at the centre of cell ``(i, j, k)``. Inside the box ``D`` is trilinear
  between cell centres and clamps to the nearest centre within half a cell of the faces. Outside the
  box ``D`` is zero.
* ``sigma_t(x) = density_scale * D(x)`` per world unit.

Grid coordinates ``u`` are continuous cell coordinates: cell ``i`` spans ``u in [i, i + 1]`` and its
centre is at ``i + 0.5``; ``u = (x - box.lo) / voxel_size``.
"""

from __future__ import annotations

import hashlib
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from nrc.errors import ConfigError
from nrc.volume.box import Box


class CellField:
    """A cell-centred field on the grid, sampled trilinearly with clamping at the box faces.

    Wraps :func:`torch.nn.functional.grid_sample` (``align_corners=False`` puts the samples at cell
    centres; ``padding_mode="border"`` clamps within half a cell of the faces); points outside the box
    get exactly zero.

    Args:
        values: ``(nx, ny, nz)`` or ``(nx, ny, nz, C)`` values at cell centres.
    """

    def __init__(self, values: Tensor) -> None:
        self.channels = values.shape[3] if values.dim() == 4 else 0
        self._data = self._layout(values).contiguous()

    def _layout(self, values: Tensor) -> Tensor:
        """``values`` as grid_sample wants them: ``(1, C, D, H, W)`` with grid coordinates (x -> W, y -> H, z -> D)."""
        v = values if self.channels else values[..., None]
        return v.permute(3, 2, 1, 0)[None]

    def assign(self, values: Tensor) -> None:
        """Replace the values in place (same shape as at construction)."""
        self._data.copy_(self._layout(values))

    def __call__(self, s: Tensor) -> Tensor:
        """Sample at box coordinates ``s`` ``(N, 3)`` in ``[0, 1]^3``; returns ``(N,)`` or ``(N, C)``."""
        inside = ((s >= 0) & (s <= 1)).all(dim=-1)
        g = (2.0 * s - 1.0).view(1, -1, 1, 1, 3)
        out = F.grid_sample(self._data, g, mode="bilinear", padding_mode="border", align_corners=False)
        out = out.view(out.shape[1], -1).t()
        out = torch.where(inside[:, None], out, torch.zeros_like(out))
        return out if self.channels else out[:, 0]


def _normalized(field: Tensor) -> Tensor:
    """Scale a field into ``[-1, 1]`` by its largest absolute value (all-zero fields stay zero)."""
    peak = field.abs().max()
    return field / peak if peak > 0 else field.clone()


class DensityGrid:
    """A dense float32 density grid on a device, placed in a world box.

    Args:
        density: ``(nx, ny, nz)`` grid values ``D`` (finite, >= 0); copied to ``device`` as float32.
        center: world position of the box centre, 3 floats.
        diagonal: world length of the box diagonal (> 0).
        density_scale: extinction per world unit per unit of ``D`` (>= 0).
        device: torch device for all tensors.
    """

    def __init__(
        self,
        density: Tensor,
        center: tuple[float, float, float] | list[float],
        diagonal: float,
        density_scale: float,
        device: torch.device | str = "cpu",
    ) -> None:
        density = torch.as_tensor(density, dtype=torch.float32)
        if density.dim() != 3 or min(density.shape) < 1:
            raise ConfigError(f"scene.volume: density grid must be 3-D and non-empty, got shape {tuple(density.shape)}")
        if not torch.isfinite(density).all():
            raise ConfigError("scene.volume: density grid contains NaN or Inf values")
        if (density < 0).any():
            raise ConfigError("scene.volume: density grid contains negative values")
        if not (diagonal > 0 and math.isfinite(diagonal)):
            raise ConfigError(f"scene.volume.diagonal must be a positive number, got {diagonal}")
        if not (density_scale >= 0 and math.isfinite(density_scale)):
            raise ConfigError(f"scene.volume.density_scale must be >= 0, got {density_scale}")
        self.device = torch.device(device)
        self.density = density.to(self.device).contiguous()
        self.density_scale = float(density_scale)
        self.shape = tuple(int(n) for n in density.shape)
        self.voxel_size = float(diagonal) / math.sqrt(sum(n * n for n in self.shape))
        c = torch.as_tensor(center, dtype=torch.float32, device=self.device)
        half = 0.5 * self.voxel_size * torch.tensor(self.shape, dtype=torch.float32, device=self.device)
        self.box = Box(c - half, c + half)
        self._density_field = CellField(self.density)
        self._gradient: CellField | None = None
        self._laplacian: CellField | None = None
        self._values_hash: str | None = None  # fingerprint()'s hash of the values, made once

    # ---------------------------------------------------------------- transforms
    def world_to_grid(self, x: Tensor) -> Tensor:
        """World points ``(N, 3)`` -> continuous cell coordinates ``(N, 3)``."""
        return (x - self.box.lo) / self.voxel_size

    def grid_to_world(self, u: Tensor) -> Tensor:
        """Continuous cell coordinates ``(N, 3)`` -> world points ``(N, 3)``."""
        return self.box.lo + u * self.voxel_size

    def fingerprint(self) -> str:
        """A hash of what ``sigma_t`` reads: the grid's values (hashed once: they are never changed in place), its
        shape, the density scale and the box; the key of arrays derived from the medium and kept on disk
        (:func:`nrc.volume.optical_depth.light_optical_depth_field`)."""
        if self._values_hash is None:
            self._values_hash = hashlib.sha1(self.density.detach().cpu().numpy().tobytes()).hexdigest()
        box = (*self.box.lo.tolist(), *self.box.hi.tolist())
        return hashlib.sha1(repr((self._values_hash, self.shape, self.density_scale, box)).encode()).hexdigest()[:20]

    # ---------------------------------------------------------------- lookups
    @property
    def max_density(self) -> float:
        """Largest grid value ``max D`` (the trilinear field never exceeds it)."""
        return float(self.density.max())

    def lookup(self, x: Tensor) -> Tensor:
        """Grid value ``D(x)`` at world points ``(N, 3)``; zero outside the box. Returns ``(N,)``."""
        return self._density_field(self.box.normalize(x))

    def sigma_t(self, x: Tensor) -> Tensor:
        """Extinction ``density_scale * D(x)`` per world unit at world points ``(N, 3)``. Returns ``(N,)``."""
        return self.density_scale * self.lookup(x)

    # ---------------------------------------------------------------- derived fields (cache inputs)
    def gradient_field(self) -> Tensor:
        """``(nx, ny, nz, 3)`` central-difference gradient of ``D`` per world unit, scaled into ``[-1, 1]``
        by its largest component magnitude (one-sided at the faces)."""
        d = self.density
        comps = [
            torch.gradient(d, spacing=self.voxel_size, dim=a)[0] if d.shape[a] > 1 else torch.zeros_like(d)
            for a in range(3)
        ]
        return _normalized(torch.stack(comps, dim=-1))

    def laplacian_field(self) -> Tensor:
        """``(nx, ny, nz)`` 7-point Laplacian of ``D`` (edge values replicated at the faces), scaled into
        ``[-1, 1]`` by its largest magnitude."""
        d = self.density
        p = F.pad(d[None, None], (1, 1, 1, 1, 1, 1), mode="replicate")[0, 0]
        lap = (
            p[2:, 1:-1, 1:-1] + p[:-2, 1:-1, 1:-1]
            + p[1:-1, 2:, 1:-1] + p[1:-1, :-2, 1:-1]
            + p[1:-1, 1:-1, 2:] + p[1:-1, 1:-1, :-2]
            - 6.0 * d
        ) / self.voxel_size**2
        return _normalized(lap)

    def gradient(self, x: Tensor) -> Tensor:
        """Normalised density gradient at world points ``(N, 3)``; zero outside. Returns ``(N, 3)``.
        The field is computed on first use."""
        if self._gradient is None:
            self._gradient = CellField(self.gradient_field())
        return self._gradient(self.box.normalize(x))

    def laplacian(self, x: Tensor) -> Tensor:
        """Normalised density Laplacian at world points ``(N, 3)``; zero outside. Returns ``(N,)``.
        The field is computed on first use."""
        if self._laplacian is None:
            self._laplacian = CellField(self.laplacian_field())
        return self._laplacian(self.box.normalize(x))

    def normalized_density(self, x: Tensor) -> Tensor:
        """``D(x) / max D`` in ``[0, 1]`` at world points ``(N, 3)`` (zero for an all-zero grid)."""
        peak = self.max_density
        d = self.lookup(x)
        return d / peak if peak > 0 else d


Scalar = float | Tensor  # a Python float or a 0-d tensor (a scene parameter passed into compiled code)
V3 = tuple[Tensor, Tensor, Tensor]  # a batch of 3-vectors as three (S,) tensors (x, y, z)


def trilinear(flat: Tensor, shape: tuple[Scalar, Scalar, Scalar], lo: tuple[Scalar, Scalar, Scalar],
              hi: tuple[Scalar, Scalar, Scalar], x: V3) -> Tensor:
    """``D(x)`` ``(S,)`` at world points ``x`` (component form) by explicit gathers on the flattened
    ``(nx, ny, nz)`` grid ``flat`` (C order): the same field as :meth:`DensityGrid.lookup` (cell-centred
    samples, clamped within half a cell of the faces, exactly zero outside the box ``[lo, hi]``).

    ``shape``, ``lo`` and ``hi`` may be Python numbers or 0-d tensors, so that a compiled caller takes them
    as inputs (one compiled graph for every grid). Non-finite points give 0 (indices are clamped, so every
    gather is in bounds)."""
    inside = None
    i0s, i1s, fs = [], [], []
    dims = [n + torch.zeros_like(x[0]) for n in shape]  # per point: numbers or 0-d tensors alike
    for a in range(3):
        s = (x[a] - lo[a]) / (hi[a] - lo[a])
        ok = (s >= 0) & (s <= 1)
        inside = ok if inside is None else inside & ok
        u = (s * dims[a] - 0.5).nan_to_num(0.0, 0.0, 0.0).clamp(min=0.0)
        u = torch.minimum(u, dims[a] - 1.0)
        f = u.floor()
        i0 = f.long()
        i0s.append(i0)
        i1s.append(torch.minimum(i0 + 1, (dims[a] - 1.0).long()))
        fs.append(u - f)
    nz = dims[2].long()
    sx = dims[1].long() * nz
    bx = (i0s[0] * sx, i1s[0] * sx)
    by = (i0s[1] * nz, i1s[1] * nz)
    fx, fy, fz = fs

    def lerp_z(i: int, j: int) -> Tensor:
        base = bx[i] + by[j]
        return flat[base + i0s[2]] * (1 - fz) + flat[base + i1s[2]] * fz

    v = (lerp_z(0, 0) * (1 - fy) + lerp_z(0, 1) * fy) * (1 - fx) + (lerp_z(1, 0) * (1 - fy) + lerp_z(1, 1) * fy) * fx
    return torch.where(inside, v, torch.zeros_like(v))
