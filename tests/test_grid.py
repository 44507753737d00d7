"""DensityGrid: placement, cell-centred trilinear lookups with clamping, derived fields."""

import itertools
import math

import numpy as np
import pytest
import torch

from nrc.errors import ConfigError
from nrc.volume.grid import DensityGrid


def reference_lookup(D: np.ndarray, lo: np.ndarray, h: float, x: np.ndarray) -> float:
    """Independent scalar implementation of the SCENE.md interpolation rule."""
    n = np.array(D.shape)
    u = (x - lo) / h
    if np.any(u < 0) or np.any(u > n):
        return 0.0
    p = np.clip(u - 0.5, 0, n - 1)
    i0 = np.minimum(np.floor(p).astype(int), np.maximum(n - 2, 0))
    f = p - i0
    total = 0.0
    for c in itertools.product((0, 1), repeat=3):
        idx = np.minimum(i0 + np.array(c), n - 1)
        w = np.prod([f[a] if c[a] else 1 - f[a] for a in range(3)])
        total += w * D[tuple(idx)]
    return total


@pytest.fixture
def asym_grid():
    rng = np.random.default_rng(3)
    D = rng.random((4, 3, 2)).astype(np.float32)
    return D, DensityGrid(torch.from_numpy(D), center=(1.0, -2.0, 0.5), diagonal=3.0, density_scale=2.5)


def test_placement_keeps_aspect_and_cubic_cells(asym_grid):
    D, grid = asym_grid
    h = 3.0 / math.sqrt(4**2 + 3**2 + 2**2)
    assert grid.voxel_size == pytest.approx(h)
    np.testing.assert_allclose(grid.box.extent.numpy(), h * np.array([4, 3, 2]), rtol=1e-6)
    np.testing.assert_allclose(grid.box.center.numpy(), [1.0, -2.0, 0.5], atol=1e-6)
    assert float(grid.box.extent.norm()) == pytest.approx(3.0, rel=1e-6)


def test_cell_centres_hold_the_grid_values(asym_grid):
    D, grid = asym_grid
    idx = torch.tensor(list(itertools.product(range(4), range(3), range(2))), dtype=torch.float32)
    x = grid.grid_to_world(idx + 0.5)
    got = grid.lookup(x).numpy()
    want = np.array([D[tuple(i)] for i in idx.long().tolist()])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_trilinear_matches_hand_computation(asym_grid):
    """Random points inside, in the half-cell clamp zone and outside; an axis swap or offset would fail."""
    D, grid = asym_grid
    rng = np.random.default_rng(4)
    lo, hi = grid.box.lo.numpy(), grid.box.hi.numpy()
    pts = lo + rng.uniform(-0.1, 1.1, size=(500, 3)) * (hi - lo)
    got = grid.lookup(torch.from_numpy(pts.astype(np.float32))).numpy()
    want = np.array([reference_lookup(D, lo, grid.voxel_size, p) for p in pts])
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    assert (want == 0).sum() > 50  # some points really were outside


def test_hand_computed_point():
    """A single point worked out by hand on a 2x2x2 grid."""
    D = torch.zeros(2, 2, 2)
    D[1, 0, 0] = 8.0  # +x corner cell
    D[0, 1, 1] = 4.0
    grid = DensityGrid(D, center=(1.0, 1.0, 1.0), diagonal=2.0 * math.sqrt(3.0), density_scale=1.0)
    # Box [0,2]^3, cell centres at 0.5 and 1.5. Point (1.25, 0.5, 0.5): fx = 0.75, fy = fz = 0.
    assert float(grid.lookup(torch.tensor([[1.25, 0.5, 0.5]]))) == pytest.approx(6.0)
    # (0.5, 1.0, 1.0): fx = 0, fy = fz = 0.5 -> 0.25 * D[0,1,1] = 1
    assert float(grid.lookup(torch.tensor([[0.5, 1.0, 1.0]]))) == pytest.approx(1.0)
    # clamp zone: (1.9, 0.1, 0.1) clamps to the centre of cell (1,0,0)
    assert float(grid.lookup(torch.tensor([[1.9, 0.1, 0.1]]))) == pytest.approx(8.0)
    # outside: zero
    assert float(grid.lookup(torch.tensor([[2.01, 0.5, 0.5]]))) == 0.0
    assert float(grid.sigma_t(torch.tensor([[1.25, 0.5, 0.5]]))) == pytest.approx(6.0)


def test_single_cell_axis_is_constant_along_it():
    D = torch.arange(6, dtype=torch.float32).reshape(3, 2, 1)
    grid = DensityGrid(D, (0, 0, 0), 1.0, 1.0)
    x = grid.grid_to_world(torch.tensor([[0.5, 0.5, 0.1], [0.5, 0.5, 0.9]]))
    v = grid.lookup(x)
    torch.testing.assert_close(v, D[0, 0, 0].expand(2), atol=1e-6, rtol=0)


def test_gradient_and_laplacian_fields_are_normalised():
    x = torch.linspace(0, 1, 10)
    D = (x[:, None, None] ** 2).expand(10, 6, 5).contiguous()  # varies along x only
    grid = DensityGrid(D, (0, 0, 0), 2.0, 1.0)
    g = grid.gradient_field()
    assert g.shape == (10, 6, 5, 3)
    assert float(g.abs().max()) == pytest.approx(1.0)
    assert float(g[..., 1:].abs().max()) == 0.0 and float(g[..., 0].min()) >= 0
    lap = grid.laplacian_field()
    assert float(lap.abs().max()) == pytest.approx(1.0)
    pts = grid.grid_to_world(torch.tensor([[5.0, 3.0, 2.5]]))
    assert grid.gradient(pts).shape == (1, 3) and grid.laplacian(pts).shape == (1,)
    outside = grid.box.hi[None] + 1.0
    assert float(grid.gradient(outside).abs().sum()) == 0.0


@pytest.mark.parametrize(
    "D, kwargs, key",
    [
        (torch.ones(2, 2, 2), {"density_scale": -1.0}, "density_scale"),
        (torch.ones(2, 2, 2), {"diagonal": 0.0}, "diagonal"),
        (-torch.ones(2, 2, 2), {}, "negative"),
        (torch.full((2, 2, 2), float("nan")), {}, "NaN"),
        (torch.ones(2, 2), {}, "3-D"),
    ],
)
def test_bad_grids_raise_config_error(D, kwargs, key):
    args = {"center": (0, 0, 0), "diagonal": 1.0, "density_scale": 1.0, **kwargs}
    with pytest.raises(ConfigError, match=key):
        DensityGrid(D, **args)
