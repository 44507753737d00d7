"""Delta tracking free-flight sampling: distance distribution, majorant checks, DDA walk, hard cases."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from nrc.transport.tracking import (
    MajorantError,
    TrackingStats,
    clip_segments,
    majorant_segments,
    optical_depth_bounds,
    sample_free_flight,
)
from conftest import constant_grid, hard_rays, spike_grid, unit
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import MajorantGrid, skip_radius


pytestmark = pytest.mark.usefixtures("single_thread")


def trilinear_grid():
    gen = torch.Generator().manual_seed(0)
    return DensityGrid(torch.rand(9, 6, 7, generator=gen) ** 2, center=(0, 0, 0), diagonal=3.0, density_scale=4.0)


def sparse_grid():
    """Mostly empty box with one asymmetric lump: exercises empty-space skipping (skip radius > 1)."""
    gen = torch.Generator().manual_seed(1)
    D = torch.zeros(24, 20, 22)
    D[13:19, 5:11, 6:10] = torch.rand(6, 6, 4, generator=gen) * torch.linspace(0.2, 1.0, 4)
    return DensityGrid(D, center=(1.0, 0.0, -0.5), diagonal=6.0, density_scale=3.0)


GRIDS = {"constant": constant_grid, "trilinear": trilinear_grid, "sparse": sparse_grid}


def some_rays(grid, which):
    """A few rays through the grid: from outside (two), from inside (one)."""
    c = grid.box.center
    ext = grid.box.extent
    if which == "sparse":
        target = grid.box.lo + torch.tensor([16.0, 8.0, 8.0]) / torch.tensor([24.0, 20.0, 22.0]) * ext
        o = torch.stack([c - ext * torch.tensor([0.9, 0.7, 0.8]), c + ext * torch.tensor([0.8, 0.1, 0.9]), target])
        d = torch.stack([target - o[0], target - o[1], torch.tensor([0.3, -0.4, 0.5])])
    else:
        o = torch.stack([c - ext * torch.tensor([0.9, 0.3, 0.2]), c + ext * torch.tensor([0.1, 0.9, -0.2]), c + 0.1 * ext])
        d = torch.stack([torch.tensor([1.0, 0.3, 0.25]), torch.tensor([-0.1, -1.0, 0.15]), torch.tensor([0.4, -0.3, -0.6])])
    return o, unit(d)


def optical_depth_table(grid, o, d, a, b, n=20001):
    """Exact tau(t) on [a, b] by fine trapezoid quadrature (float64 accumulation). Returns (t, tau(t))."""
    t = np.linspace(a, b, n)
    x = torch.as_tensor(o, dtype=torch.float64)[None] + torch.as_tensor(t)[:, None] * torch.as_tensor(d, dtype=torch.float64)[None]
    sig = grid.sigma_t(x.to(torch.float32)).double().numpy()
    tau = np.concatenate(([0.0], np.cumsum(0.5 * (sig[1:] + sig[:-1]) * np.diff(t))))
    return t, tau


@pytest.mark.parametrize("which", list(GRIDS))
@pytest.mark.parametrize("mode", ["global", "brick"])
def test_collision_distances_follow_exp_minus_tau(which, mode):
    grid = GRIDS[which]()
    mg = MajorantGrid(grid, brick=2)
    o, d = some_rays(grid, which)
    oc, a, b = clip_segments(grid, o, d, None, None)
    assert bool((b > a).all())
    n = 4000
    gen = torch.Generator().manual_seed(42)
    t, hit, st = sample_free_flight(grid, mg, o.repeat_interleave(n, 0), d.repeat_interleave(n, 0), None, gen, mode=mode,
                                    return_stats=True)
    assert isinstance(st, TrackingStats) and st.lookups > 0 and st.rays == 3 * n
    t, hit = t.view(3, n), hit.view(3, n)
    for r in range(3):
        ts, tau = optical_depth_table(grid, o[r].double(), d[r].double(), float(a[r]), float(b[r]))
        p_hit = 1.0 - math.exp(-tau[-1])
        se = math.sqrt(p_hit * (1 - p_hit) / n)
        assert abs(float(hit[r].float().mean()) - p_hit) < 4 * se + 1e-3
        # escaped rays report t_max (= inf here); collisions lie inside the segment
        assert bool(torch.isinf(t[r][~hit[r]]).all())
        th = t[r][hit[r]].double().numpy()
        assert th.min() >= ts[0] - 1e-5 and th.max() <= ts[-1] + 1e-5

        def cdf(v):
            return (1.0 - np.exp(-np.interp(v, ts, tau))) / p_hit

        res = stats.kstest(th, cdf)
        assert res.pvalue > 1e-3, (which, mode, r, res)


def test_t_max_limits_collisions_and_is_returned_on_escape():
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d = some_rays(grid, "trilinear")
    n = 3000
    O, Dd = o.repeat_interleave(n, 0), d.repeat_interleave(n, 0)
    _, a, b = clip_segments(grid, o, d, None, None)
    t_max = (a + 0.4 * (b - a)).repeat_interleave(n)
    for mode in ("global", "brick"):
        t, hit = sample_free_flight(grid, mg, O, Dd, t_max, torch.Generator().manual_seed(3), mode=mode)
        assert bool((t[hit] < t_max[hit]).all())
        assert torch.equal(t[~hit], t_max[~hit])
        for r in range(3):
            ts, tau = optical_depth_table(grid, o[r].double(), d[r].double(), float(a[r]), float(t_max[r * n]))
            p_hit = 1.0 - math.exp(-tau[-1])
            assert abs(float(hit[r * n:(r + 1) * n].float().mean()) - p_hit) < 4 * math.sqrt(p_hit * (1 - p_hit) / n) + 1e-3
    # a scalar t_max works too
    t, hit = sample_free_flight(grid, mg, O[:10], Dd[:10], 0.0, torch.Generator().manual_seed(3))
    assert not hit.any() and bool((t == 0).all())


def test_same_seed_same_result():
    grid = sparse_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d = some_rays(grid, "sparse")
    O, Dd = o.repeat_interleave(500, 0), d.repeat_interleave(500, 0)
    for mode in ("global", "brick"):
        r1 = sample_free_flight(grid, mg, O, Dd, None, torch.Generator().manual_seed(7), mode=mode)
        r2 = sample_free_flight(grid, mg, O, Dd, None, torch.Generator().manual_seed(7), mode=mode)
        assert torch.equal(r1[0], r2[0]) and torch.equal(r1[1], r2[1])


def test_brick_mode_skips_empty_space():
    grid = sparse_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d = some_rays(grid, "sparse")
    O, Dd = o.repeat_interleave(1000, 0), d.repeat_interleave(1000, 0)
    sg, sb = TrackingStats(), TrackingStats()
    _, _, sg = sample_free_flight(grid, mg, O, Dd, None, torch.Generator().manual_seed(1), mode="global", return_stats=True)
    _, _, sb = sample_free_flight(grid, mg, O, Dd, None, torch.Generator().manual_seed(1), mode="brick", return_stats=True)
    assert sb.lookups < 0.5 * sg.lookups
    # jumps over empty cubes: far fewer brick steps than bricks pierced
    n_bricks_per_ray = sum(mg.shape)
    assert sb.advances < 3000 * n_bricks_per_ray / 3


def test_skip_radius_is_the_chebyshev_distance_to_the_nearest_nonempty_brick():
    D = torch.zeros(20, 16, 12)
    D[9, 5, 3] = 1.0  # brick (4, 2, 1) with brick = 2, plus its one-cell dilation into neighbours
    grid = DensityGrid(D, center=(0, 0, 0), diagonal=5.0, density_scale=1.0)
    mg = MajorantGrid(grid, brick=2)
    r = skip_radius(mg)
    nonempty = torch.nonzero(mg.majorant > 0)
    idx = torch.stack(torch.meshgrid(*[torch.arange(s) for s in mg.shape], indexing="ij"), dim=-1)
    dist = (idx[..., None, :] - nonempty[None, None, None]).abs().amax(dim=-1).amin(dim=-1)
    torch.testing.assert_close(r, dist.clamp(max=16).to(torch.float32))
    # cached, and recomputed when the majorant changes in place
    assert skip_radius(mg) is r
    mg.majorant.zero_()
    assert bool((skip_radius(mg) >= 1).all())


def test_optical_depth_bounds_are_the_walks_segments_and_the_bricks_integral():
    """The bounds equal the sum over the walk's segments (the iterator equi-angular sampling uses) and a fine
    quadrature of the brick majorant / minorant along the ray."""
    grid = trilinear_grid()
    for brick in (1, 2, 3, 8):
        mg = MajorantGrid(grid, brick=brick)
        gen = torch.Generator().manual_seed(brick)
        o = grid.box.center + torch.randn(300, 3, generator=gen) * 2.0
        d = unit(grid.box.lo + torch.rand(300, 3, generator=gen) * grid.box.extent - o)
        oc, a, b = clip_segments(grid, o, d, None, None)
        hi, lo = optical_depth_bounds(mg, oc, d, a, b)
        seg_hi, seg_lo = torch.zeros_like(a), torch.zeros_like(a)
        for _, s0, s1, maj, mnr in majorant_segments(mg, oc, d, a, b):
            seg_hi, seg_lo = seg_hi + (s1 - s0) * maj, seg_lo + (s1 - s0) * mnr
        torch.testing.assert_close(hi, seg_hi, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(lo, seg_lo, rtol=1e-5, atol=1e-5)
        n = 4000
        s = (torch.arange(n) + 0.5) / n
        x = oc[:, None, :] + (a[:, None] + s[None, :] * (b - a)[:, None])[..., None] * d[:, None, :]
        cell = ((x - mg.origin) / mg.brick_size).floor().long()
        cell = torch.minimum(cell.clamp(min=0), torch.tensor(mg.shape) - 1)
        quad = mg.majorant[cell[..., 0], cell[..., 1], cell[..., 2]].mean(1) * (b - a)
        torch.testing.assert_close(hi, quad, rtol=2e-2, atol=2e-2)


@pytest.mark.parametrize("mode", ["global", "brick"])
def test_underestimated_majorant_raises(mode):
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    mg.majorant.mul_(0.5)
    mg.global_majorant *= 0.5
    o, d = some_rays(grid, "trilinear")
    with pytest.raises(MajorantError):
        sample_free_flight(grid, mg, o.repeat(200, 1), d.repeat(200, 1), None, torch.Generator().manual_seed(0), mode=mode)
    # a stale majorant grid after a density-scale change is caught the same way
    grid2 = trilinear_grid()
    mg2 = MajorantGrid(grid2, brick=2)
    grid2.density_scale *= 3.0
    with pytest.raises(MajorantError):
        sample_free_flight(grid2, mg2, o.repeat(200, 1), d.repeat(200, 1), None, torch.Generator().manual_seed(0), mode=mode)





@pytest.mark.parametrize(
    "make",
    [
        lambda: DensityGrid(torch.rand(5, 4, 6), center=(0, 0, 0), diagonal=2.0, density_scale=0.0),
        lambda: DensityGrid(torch.rand(5, 4, 6), center=(0, 0, 0), diagonal=2.0, density_scale=1e4),
        lambda: DensityGrid(torch.zeros(5, 4, 6), center=(0, 0, 0), diagonal=2.0, density_scale=1.0),
        spike_grid,
        trilinear_grid,
    ],
    ids=["scale0", "scale1e4", "empty", "spike", "trilinear"],
)
@pytest.mark.parametrize("mode", ["global", "brick"])
def test_hard_cases_terminate_and_stay_finite(make, mode):
    grid = make()
    mg = MajorantGrid(grid, brick=2)
    o, d = hard_rays(grid)
    O, Dd = o.repeat(50, 1), d.repeat(50, 1)
    t, hit = sample_free_flight(grid, mg, O, Dd, None, torch.Generator().manual_seed(0), mode=mode)
    assert torch.isfinite(t[hit]).all()
    assert not hit.view(50, -1)[:, 6:].any()  # misses never collide
    if mg.global_majorant == 0:
        assert not hit.any()
    _, a, b = clip_segments(grid, O, Dd, None, None)
    assert bool((t[hit] >= a[hit] - 1e-5).all() and (t[hit] <= b[hit] + 1e-5).all())
    if grid.density_scale == 1e4:
        # a ray from inside a dense medium collides almost at once
        assert hit.view(50, -1)[:, 0].all()
