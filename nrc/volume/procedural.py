"""The built-in procedural cumulus cloud: the project's default volume, no download needed.

The cloud is a union of soft spherical blobs resting on a flat base, its surface displaced and its
interior modulated by fractal value noise. Everything is drawn from one ``torch.Generator`` seeded with
``seed`` on the CPU, so the same ``(resolution, seed)`` gives the same grid on every machine and device.
Values are in ``[0, 1]`` (0 outside the cloud); index ``(i, j, k)`` runs along world ``(+x, +y, +z)``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def _fbm(shape: tuple[int, int, int], octaves: int, base: int, gen: torch.Generator) -> Tensor:
    """Fractal value noise in roughly ``[-1, 1]``: random lattices of ``base * 2^o`` points upsampled."""
    out = torch.zeros(shape)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = base * 2**o
        lattice = torch.rand((1, 1, n, n, n), generator=gen) * 2.0 - 1.0
        out += amp * F.interpolate(lattice, size=shape, mode="trilinear", align_corners=True)[0, 0]
        total += amp
        amp *= 0.5
    return out / total


def _smoothstep(e0: float, e1: float, x: Tensor) -> Tensor:
    t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def procedural_cloud(resolution: tuple[int, int, int] | list[int] | int = 128, seed: int = 0) -> Tensor:
    """Generate a cumulus-like density grid.

    Args:
        resolution: ``(nx, ny, nz)`` or one int for a cube; each >= 8.
        seed: random seed (any int); the result is a deterministic function of ``(resolution, seed)``.

    Returns:
        float32 tensor ``(nx, ny, nz)`` on the CPU with values in ``[0, 1]``.
    """
    res = (resolution,) * 3 if isinstance(resolution, int) else tuple(int(r) for r in resolution)
    if len(res) != 3 or min(res) < 8:
        raise ValueError(f"procedural cloud resolution must be 3 ints >= 8, got {resolution}")
    gen = torch.Generator().manual_seed(int(seed))
    # Cell-centre coordinates in [-1, 1] along each axis (y up).
    axes = [(torch.arange(n, dtype=torch.float32) + 0.5) / n * 2.0 - 1.0 for n in res]
    x, y, z = torch.meshgrid(*axes, indexing="ij")

    # Blobs: a big central tower and smaller shoulders around it, bottoms near the base plane.
    n_blobs = 9
    u = torch.rand((n_blobs, 4), generator=gen)
    radius = 0.28 + 0.22 * u[:, 0]
    radius[0] = 0.55
    ang = 2.0 * torch.pi * u[:, 1]
    dist = 0.15 + 0.4 * u[:, 2]
    dist[0] = 0.0
    cx, cz = dist * torch.cos(ang), dist * torch.sin(ang)
    base = -0.7
    cy = base + radius * (0.55 + 0.35 * u[:, 3])
    shape = torch.full(res, -1.0)
    for b in range(n_blobs):  # a handful of blobs: loop over blobs, not voxels
        d = torch.sqrt((x - cx[b]) ** 2 + ((y - cy[b]) * 1.15) ** 2 + (z - cz[b]) ** 2)
        shape = torch.maximum(shape, 1.0 - d / radius[b])

    surface = _fbm(res, octaves=4, base=4, gen=gen)
    detail = _fbm(res, octaves=3, base=8, gen=gen)
    shape = shape + 0.28 * surface
    flat_base = _smoothstep(base, base + 0.12, y)
    density = _smoothstep(0.0, 0.22, shape) * flat_base * (0.75 + 0.25 * detail)
    return density.clamp(0.0, 1.0).contiguous()
