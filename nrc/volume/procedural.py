"""The built-in procedural clouds: the project's default volumes, no download needed.

``scene.volume.procedural.kind`` chooses the generator:

=================  ==================================================================================
``cumulus``        (default) a heaped cumulus: a hierarchy of blobs (a few big ones on a flat base,
                   smaller ones grown on their upper surfaces: the cauliflower top), its surface eroded
                   by billowy cellular (Worley) noise at two scales and fractal value noise, cut flat at
                   the base. Generation lattice aspect x:y:z = 1 : 0.8 : 1.
``stratocumulus``  a thin slab of broken cloud: cells of cellular noise over a low-frequency coverage
                   field leave gaps between cloudlets, bumpy tops, a nearly flat base.
                   Lattice aspect 1 : 0.25 : 1.
``blobs``          the original generator (a union of soft spheres on a flat base, displaced by value
                   noise) on a cube lattice, unchanged so earlier experiments reproduce bit for bit.
=================  ==================================================================================

``resolution`` is one int (the lattice's longest axis; the other axes follow the kind's aspect, with cubic
voxels) or three ints (the lattice itself). ``cumulus`` and ``stratocumulus`` are then cropped to the
density's bounding box plus one empty voxel on each side, so the box the renderer traverses holds the
cloud and little else (``blobs`` keeps its lattice). The noise lattices are drawn in the generator's own
coordinates, not per voxel, so another resolution samples the same cloud more or less finely.

Everything is drawn from one ``torch.Generator`` seeded with ``seed`` on the CPU, so the same
``(kind, resolution, seed)`` gives the same grid on every machine and device. Values are in ``[0, 1]``
(0 outside the cloud); index ``(i, j, k)`` runs along world ``(+x, +y, +z)`` (y up). Memory: a few float32
copies of the lattice (~0.5 GB at 256^3); cellular noise is evaluated on at most a 96^3 lattice and
upsampled (its cells span >= 8 voxels there), which bounds the time (scripts/bench_procedural.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nrc.io.disk_cache import cached_array

KINDS = ("cumulus", "stratocumulus", "blobs")
ASPECT = {"cumulus": (1.0, 0.8, 1.0), "stratocumulus": (1.0, 0.25, 1.0), "blobs": (1.0, 1.0, 1.0)}
NOISE_LATTICE = 96  # longest axis of the lattice on which cellular noise is evaluated before upsampling


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


def _resolution(resolution: tuple[int, ...] | list[int] | int, aspect: tuple[float, float, float]) -> tuple:
    if isinstance(resolution, int):
        res = tuple(max(8, int(round(resolution * a))) for a in aspect)
        if resolution < 8:
            raise ValueError(f"procedural cloud resolution must be >= 8, got {resolution}")
        return res
    res = tuple(int(r) for r in resolution)
    if len(res) != 3 or min(res) < 8:
        raise ValueError(f"procedural cloud resolution must be 3 ints >= 8, got {resolution}")
    return res


def _coordinates(res: tuple[int, int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """Cell-centre coordinates with cubic voxels: the longest axis spans [-1, 1], the others centred."""
    m = max(res)
    axes = [((torch.arange(n, dtype=torch.float32) + 0.5) - 0.5 * n) / m * 2.0 for n in res]
    return torch.meshgrid(*axes, indexing="ij")


class _Noise:
    """Seeded noise fields defined in the generator's coordinates (``[-1, 1]`` along the longest axis), so a
    field is the same function whatever lattice samples it."""

    def __init__(self, res: tuple[int, int, int], gen: torch.Generator) -> None:
        self.res, self.gen = res, gen
        m = max(res)
        self.extent = tuple(n / m for n in res)  # half-extent of the lattice along each axis

    def _voxel_grid(self) -> Tensor:
        """``grid_sample`` coordinates of every voxel in a lattice that tiles ``[-1, 1]`` once per axis (the
        period is the longest axis' span): ``(1, nx, ny, nz, 3)``, ordered (k, j, i) as grid_sample wants."""
        grids = []
        for n, e in zip(self.res, self.extent):
            p = ((torch.arange(n, dtype=torch.float32) + 0.5) / n * 2.0 - 1.0) * e
            grids.append((p / 2.0) % 1.0 * 2.0 - 1.0)
        x, y, z = torch.meshgrid(*grids, indexing="ij")
        return torch.stack([z, y, x], -1)[None]

    @staticmethod
    def _sample(field: Tensor, grid: Tensor) -> Tensor:
        """Trilinear lookup of the periodic lattice ``field`` at the voxels of :meth:`_voxel_grid`."""
        pad = torch.cat([field, field[:1]], 0)
        pad = torch.cat([pad, pad[:, :1]], 1)
        pad = torch.cat([pad, pad[:, :, :1]], 2)  # wrap: index c equals index 0
        # with align_corners, -1 .. 1 spans the padded lattice's c + 1 points, i.e. exactly one period
        return F.grid_sample(pad[None, None], grid, mode="bilinear", align_corners=True)[0, 0]

    def worley(self, cells: int) -> Tensor:
        """Billowy cellular noise ``1 - F1`` in ``[0, 1]``: one random feature point per cell of a periodic
        ``cells^3`` tiling of ``[-1, 1]^3`` (F1 = distance to the nearest, in cell units, clamped to 1).
        Evaluated on a lattice with >= 8 samples per cell (at most the voxel lattice) and upsampled."""
        c = cells
        pts = torch.rand((c, c, c, 3), generator=self.gen)
        m = max(self.res)
        coarse_m = min(m, max(8 * c, NOISE_LATTICE))
        shape = tuple(max(2, round(n * coarse_m / m)) for n in self.res)
        q = [((torch.arange(n, dtype=torch.float32) + 0.5) / n * 2.0 - 1.0) * e for n, e in zip(shape, self.extent)]
        gx, gy, gz = torch.meshgrid(*[(a + 1.0) * 0.5 * c for a in q], indexing="ij")  # in cell units
        cx, cy, cz = (torch.floor(a).long() for a in (gx, gy, gz))
        best = torch.full(shape, float("inf"))
        for dx in (-1, 0, 1):  # 27 neighbouring cells: loop over offsets, not voxels
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    ix, iy, iz = cx + dx, cy + dy, cz + dz
                    p = pts[ix % c, iy % c, iz % c]
                    d2 = (ix + p[..., 0] - gx) ** 2 + (iy + p[..., 1] - gy) ** 2 + (iz + p[..., 2] - gz) ** 2
                    best = torch.minimum(best, d2)
        f1 = 1.0 - torch.sqrt(best).clamp(max=1.0)
        if shape == tuple(self.res):
            return f1
        return F.interpolate(f1[None, None], size=self.res, mode="trilinear", align_corners=False)[0, 0]

    def value(self, cells: int, octaves: int) -> Tensor:
        """Fractal value noise in about ``[-1, 1]``: periodic random lattices of ``cells * 2^o`` points."""
        out = torch.zeros(self.res)
        grid = self._voxel_grid()  # the same lookup coordinates for every octave
        amp, total = 1.0, 0.0
        for o in range(octaves):
            c = cells * 2**o
            lattice = torch.rand((c, c, c), generator=self.gen) * 2.0 - 1.0
            out += amp * self._sample(lattice, grid)
            total += amp
            amp *= 0.5
        return out / total


def _smooth_union(sd: Tensor, d: Tensor, k: float) -> Tensor:
    """Polynomial smooth minimum of two signed distances (blend width ``k``)."""
    h = (0.5 + 0.5 * (d - sd) / k).clamp(0.0, 1.0)
    return d + (sd - d) * h - k * h * (1.0 - h)


def _cumulus(res: tuple[int, int, int], gen: torch.Generator) -> Tensor:
    x, y, z = _coordinates(res)
    noise = _Noise(res, gen)
    ey = noise.extent[1]
    base = -0.62 * ey
    # Level 0: a central tower (stacked blobs) and shoulders on the base; levels 1 and 2: smaller blobs grown on
    # the upper surfaces of the level before (the cauliflower top).
    blobs: list[tuple[float, float, float, float]] = []
    u = torch.rand((2 + 7, 3), generator=gen).tolist()
    for i, (a, b, c) in enumerate(u[:2]):  # the tower
        r = 0.36 - 0.06 * i
        blobs.append((0.1 * (a - 0.5), base + 0.22 + 0.28 * i, 0.1 * (b - 0.5), r))
    for a, b, c in u[2:]:  # shoulders, lower and farther out
        r = 0.2 + 0.1 * a
        ang, dist = 2.0 * math.pi * b, 0.22 + 0.2 * c
        blobs.append((dist * math.cos(ang), base + 0.7 * r, dist * math.sin(ang), r))
    start = 0
    for count, shrink in ((14, 0.5), (28, 0.45)):
        parents, start = blobs[start:], len(blobs)
        for a, b, c, e in torch.rand((count, 4), generator=gen).tolist():
            px, py, pz, pr = parents[int(a * len(parents)) % len(parents)]
            cos_t = 0.1 + 0.9 * b  # the upper part of the parent
            sin_t = math.sqrt(1.0 - cos_t * cos_t)
            phi = 2.0 * math.pi * c
            r = pr * shrink * (0.75 + 0.5 * e)
            s = pr * 0.8
            blobs.append((px + s * sin_t * math.cos(phi), py + s * cos_t, pz + s * sin_t * math.sin(phi), r))
    # Fit the heap to the lattice: x/z within +-0.92 of the half-extent, the base at `base`.
    lo = [min(b[i] - b[3] for b in blobs) for i in range(3)]
    hi = [max(b[i] + b[3] for b in blobs) for i in range(3)]
    scale = min(0.92 * 2.0 * noise.extent[0] / (hi[0] - lo[0]), 0.92 * 2.0 * noise.extent[2] / (hi[2] - lo[2]),
                0.95 * (ey - base) / (hi[1] - base))
    mid_x, mid_z = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[2] + hi[2])
    blobs = [((bx - mid_x) * scale, base + (by - base) * scale, (bz - mid_z) * scale, r * scale)
             for bx, by, bz, r in blobs]
    # Signed distance to the smooth union, evaluated only within REACH of each blob: beyond it the distance
    # exceeds the most the erosion below can pull the surface out (0.08 + 0.032 + 0.025), so density stays 0.
    reach = 0.2
    axes = [x[:, 0, 0], y[0, :, 0], z[0, 0, :]]
    sd = torch.full(res, 10.0)
    for centre_radius in blobs:  # a few dozen blobs: loop over blobs, not voxels
        r = centre_radius[3]
        box = []
        for a, c in zip(axes, centre_radius[:3]):
            inside = torch.nonzero((a - c).abs() <= r + reach).flatten()
            box.append(slice(int(inside[0]), int(inside[-1]) + 1) if len(inside) else slice(0, 0))
        bx_, by_, bz_ = (a[sl] for a, sl in zip(axes, box))
        d = torch.sqrt((bx_[:, None, None] - centre_radius[0]) ** 2 + (by_[None, :, None] - centre_radius[1]) ** 2
                       + (bz_[None, None, :] - centre_radius[2]) ** 2) - r
        sd[box[0], box[1], box[2]] = _smooth_union(sd[box[0], box[1], box[2]], d, 0.03)
    big, small = noise.worley(7), noise.worley(17)
    fine = noise.value(12, 3)
    # Erode: push the surface in where the billows are low (round puffs at two scales), plus a little value
    # noise for ragged edges; more erosion higher up (wispier tops).
    height = ((y - base) / (2.0 * ey)).clamp(0.0, 1.0)
    sd = sd + 0.2 * (0.6 - big) + 0.08 * (0.6 - small) + 0.025 * fine + 0.03 * height
    density = _smoothstep(0.0, 0.04, -sd) * (0.75 + 0.25 * big)
    density = density * _smoothstep(base, base + 0.015, y)
    return density.clamp(0.0, 1.0)


def _stratocumulus(res: tuple[int, int, int], gen: torch.Generator) -> Tensor:
    x, y, z = _coordinates(res)
    noise = _Noise(res, gen)
    ey = noise.extent[1]
    ex, ez = noise.extent[0], noise.extent[2]
    coverage = noise.value(3, 3)  # low-frequency field: where the deck is thick or broken
    cells = noise.worley(9)  # cloudlets
    small = noise.worley(22)
    base, top = -0.55 * ey, 0.1 * ey
    bump = (0.6 * cells + 0.4 * small - 0.5) * 0.9 * ey
    thickness = _smoothstep(base, base + 0.02, y) * _smoothstep(0.0, 0.06, top + bump - y)
    broken = _smoothstep(0.0, 0.12, 0.55 * cells + 0.25 * small + 0.3 * coverage - 0.3)
    edge = (_smoothstep(0.0, 0.15, 1.0 - x.abs() / ex) * _smoothstep(0.0, 0.15, 1.0 - z.abs() / ez))
    return (thickness * broken * edge * (0.7 + 0.3 * small)).clamp(0.0, 1.0)


def _blobs(res: tuple[int, int, int], gen: torch.Generator) -> Tensor:
    """The original generator (kept verbatim: earlier results reproduce)."""
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
    return density.clamp(0.0, 1.0)


def crop_to_density(density: Tensor, margin: int = 1) -> Tensor:
    """The sub-grid holding every voxel with density > 0, plus ``margin`` empty voxels on each side."""
    nz = density > 0
    if not bool(nz.any()):
        return density
    out = density
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        idx = torch.nonzero(nz.any(dim=other)).flatten()
        lo, hi = int(idx[0]), int(idx[-1]) + 1
        out = out.narrow(axis, lo, hi - lo)
        nz = nz.narrow(axis, lo, hi - lo)
    return F.pad(out[None, None], (margin,) * 6)[0, 0]


_GENERATORS = {"cumulus": _cumulus, "stratocumulus": _stratocumulus, "blobs": _blobs}


def procedural_cloud(resolution: tuple[int, int, int] | list[int] | int = 128, seed: int = 0,
                     kind: str = "blobs") -> Tensor:
    """Generate a cloud density grid (see the module docstring for the kinds).

    Args:
        resolution: one int (longest lattice axis, the kind's aspect for the others) or ``(nx, ny, nz)``;
            each >= 8.
        seed: random seed (any int); the result is a deterministic function of ``(kind, resolution, seed)``.
        kind: ``cumulus``, ``stratocumulus`` or ``blobs``.

    Returns:
        float32 tensor ``(nx, ny, nz)`` on the CPU with values in ``[0, 1]`` (cropped to the cloud for
        ``cumulus`` and ``stratocumulus``).
    """
    if kind not in _GENERATORS:
        raise ValueError(f"procedural cloud kind must be one of {', '.join(KINDS)}, got {kind!r}")
    res = _resolution(resolution, ASPECT[kind])

    def generate() -> np.ndarray:
        gen = torch.Generator().manual_seed(int(seed))
        density = _GENERATORS[kind](res, gen)
        if kind != "blobs":
            density = crop_to_density(density)
        return density.contiguous().numpy()

    # Kept on disk (nrc/io/disk_cache.py): the cumulus at 128 takes seconds to make, milliseconds to read.
    return torch.from_numpy(cached_array("procedural", (kind, res, int(seed)), [__file__], generate))


def clear_pocket(grid, centre, radius: float) -> Tensor:
    """The grid's density with the voxels whose centres lie within ``radius`` (world units) of ``centre`` set to
    zero: a pocket of clear air (a lantern's glass housing) around a light inside the medium. Trilinear lookups
    are zero within about ``radius - sqrt(3) x voxel size`` of the centre. Returns a new ``(nx, ny, nz)`` tensor
    (write it to ``.npz`` for ``scene.volume.source=npz`` with the grid's ``diagonal`` and ``center``)."""
    idx = torch.stack(torch.meshgrid(*[torch.arange(k, device=grid.device) for k in grid.shape], indexing="ij"), -1)
    centres = grid.box.lo + (idx.float() + 0.5) * grid.voxel_size
    c = torch.as_tensor(centre, dtype=torch.float32, device=grid.device)
    return grid.density * ((centres - c).norm(dim=-1) > radius)
