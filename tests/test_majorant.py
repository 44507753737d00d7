"""Brick majorant grid: conservative bounds, and the brick walk covers each ray segment exactly once."""

import pytest
import torch

from nrc.volume.grid import DensityGrid
from nrc.transport.tracking import majorant_segments, optical_depth_bounds
from nrc.volume.majorant import MajorantGrid


def random_rays(grid, n, gen):
    """Rays from outside and inside the box, aimed at random points in it."""
    lo, ext = grid.box.lo, grid.box.extent
    origin = torch.where(
        torch.rand(n, 1, generator=gen) < 0.5,
        grid.box.center + torch.randn(n, 3, generator=gen) * ext.norm(),
        lo + torch.rand(n, 3, generator=gen) * ext,
    )
    target = lo + torch.rand(n, 3, generator=gen) * ext
    d = target - origin
    return origin, d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("brick", [0, 1, 3, 8])
def test_majorant_bounds_every_lookup_along_random_rays(brick):
    gen = torch.Generator().manual_seed(brick)
    D = torch.rand(23, 11, 17, generator=gen) ** 6  # spiky, so tight bounds matter
    D[5, 5, 5] = 30.0  # a single hot voxel
    grid = DensityGrid(D, center=(0.3, -1.0, 2.0), diagonal=5.0, density_scale=3.0)
    mg = MajorantGrid(grid, brick=brick)
    o, d = random_rays(grid, 4000, gen)
    t0, t1 = grid.box.intersect(o, d)
    covered = torch.zeros_like(t0)
    steps = 0
    for a, s0, s1, maj, mnr in majorant_segments(mg, o, d, t0, t1):
        assert bool((s1[a] >= s0[a]).all())
        covered += torch.where(a, s1 - s0, torch.zeros_like(s0))
        for s in torch.linspace(0, 1, 11):
            x = o + (s0 + s * (s1 - s0))[:, None] * d
            sig = grid.sigma_t(x)
            # bounds are tight (no dilation): allow for rounding of points on brick faces
            tol = 1e-4 * maj + 1e-5 * mg.global_majorant
            assert bool((sig[a] <= maj[a] + tol[a]).all()), "brick majorant exceeded"
            # the minorant holds inside the box (on its faces rounding may step outside, where D = 0)
            inner = a & ((x > grid.box.lo + 1e-4) & (x < grid.box.hi - 1e-4)).all(dim=-1)
            assert bool((sig[inner] >= mnr[inner] - tol[inner]).all()), "brick minorant exceeded"
        steps += 1
        assert steps <= sum(mg.shape) + 3
    torch.testing.assert_close(covered, t1 - t0, atol=1e-4, rtol=1e-5)
    assert mg.global_majorant == pytest.approx(float(D.max()) * 3.0)


def test_optical_depth_bounds_bracket_the_optical_depth():
    gen = torch.Generator().manual_seed(7)
    D = torch.rand(16, 12, 9, generator=gen)
    grid = DensityGrid(D, center=(0, 0, 0), diagonal=4.0, density_scale=2.0)
    mg = MajorantGrid(grid, brick=4)
    o, d = random_rays(grid, 500, gen)
    t0, t1 = grid.box.intersect(o, d)
    hi, lo = optical_depth_bounds(mg, o, d, t0, t1)
    n = 2000
    s = (torch.arange(n) + 0.5) / n
    tau = sum(grid.sigma_t(o + (t0 + si * (t1 - t0))[:, None] * d) for si in s) * (t1 - t0) / n
    assert bool((tau <= hi * (1 + 1e-4) + 1e-5).all()) and bool((tau >= lo * (1 - 1e-4) - 1e-5).all())


def test_empty_bricks_of_a_sparse_grid_have_zero_majorant():
    D = torch.zeros(32, 32, 32)
    D[2:5, 2:5, 2:5] = 1.0
    grid = DensityGrid(D, (0, 0, 0), 1.0, 1.0)
    mg = MajorantGrid(grid, brick=8)
    assert mg.shape == (5, 5, 5)  # bricks on the centre lattice: a half brick... plus the clamp zones
    assert float(mg.majorant[1, 1, 1]) == 1.0  # brick 1 blends centres 0..8
    assert int((mg.majorant > 0).sum()) == 1


def test_bricks_are_tight_for_single_interpolation_cells():
    """With brick 1 the bound is the max of the 8 centres a lookup blends: no dilation."""
    D = torch.zeros(6, 6, 6)
    D[3, 3, 3] = 5.0
    grid = DensityGrid(D, (0, 0, 0), 1.0, 1.0)
    mg = MajorantGrid(grid, brick=1)
    # brick b spans centres b-1..b: the spike at centre 3 touches bricks 3 and 4 along each axis only
    assert int((mg.majorant > 0).sum()) == 8


def test_rays_missing_the_box_yield_nothing():
    grid = DensityGrid(torch.ones(4, 4, 4), (0, 0, 0), 1.0, 1.0)
    mg = MajorantGrid(grid, brick=2)
    o = torch.tensor([[5.0, 5.0, 5.0], [0.0, 0.0, -3.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t0, t1 = grid.box.intersect(o, d)
    first = next(majorant_segments(mg, o, d, t0, t1))
    assert first[0].tolist() == [False, True] and float(first[3][0]) == 0.0


def test_a_run_of_empty_bricks_is_one_segment():
    """The walk crosses an empty cube in one step: fewer segments than bricks crossed, and still an exact tiling."""
    D = torch.zeros(40, 40, 40)
    D[18:22, 18:22, 18:22] = 1.0
    grid = DensityGrid(D, center=(0, 0, 0), diagonal=3.0, density_scale=2.0)
    mg = MajorantGrid(grid, brick=1)
    o = torch.tensor([[-2.0, -0.7, 0.05]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    t0, t1 = grid.box.intersect(o, d)
    segs = list(majorant_segments(mg, o, d, t0, t1))
    torch.testing.assert_close(sum(s[2] - s[1] for s in segs), t1 - t0)
    assert len(segs) < mg.shape[0] // 2
