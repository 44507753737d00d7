"""Network inputs: box normalisation, direction representations, extra inputs from the density grid."""

import math

import pytest
import torch

from nrc.cache import build_radiance_cache
from nrc.cache.inputs import ExtraInputs, InputBuilder, spherical_coordinates
from nrc.volume.grid import DensityGrid

CACHE = {"network": {"n_neurons": 16, "n_hidden_layers": 3}, "optimizer": {"lr": 1e-2, "eps": 1e-15},
         "ema": {"alpha": 0.99}, "loss": {"target_clamp": 100.0}}


def _grid() -> DensityGrid:
    return DensityGrid(torch.rand(8, 6, 5, generator=torch.Generator().manual_seed(0)), center=(0, 0, 0),
                       diagonal=2.0, density_scale=1.0)


def test_spherical_coordinates_follow_the_envmap_convention():
    d = torch.tensor([[0, 1, 0], [0, -1, 0], [0, 0, -1], [1, 0, 0], [0, 0, 1], [-1, 0, 0]], dtype=torch.float32)
    s = spherical_coordinates(d)
    torch.testing.assert_close(s[:, 0], torch.tensor([0.0, 1.0, 0.5, 0.5, 0.5, 0.5]))
    torch.testing.assert_close(s[2:, 1], torch.tensor([0.0, 0.25, 0.5, 0.75]))


def test_azimuth_wraps_into_unit_interval():
    # Tiny negative azimuths (x slightly < 0 facing -z) must land just below 1 or at 0, never at 1.
    d = torch.tensor([[-1e-9, 0.0, -1.0], [-1e-3, 0.2, -1.0], [1e-9, 0.0, -1.0], [0.0, 0.0, 1.0]])
    phi = spherical_coordinates(d)[:, 1]
    assert ((phi >= 0.0) & (phi < 1.0)).all()
    # phi and phi + 2 pi agree: directions built from angles a and a + 2 pi give the same coordinate.
    a = torch.linspace(-math.pi, math.pi, 17)
    for shift in (0.0, 2 * math.pi):
        dirs = torch.stack((torch.sin(a + shift), torch.zeros_like(a), -torch.cos(a + shift)), dim=1)
        if shift == 0.0:
            base = spherical_coordinates(dirs)[:, 1]
        else:
            diff = (spherical_coordinates(dirs)[:, 1] - base).abs()
            assert (torch.minimum(diff, 1 - diff) < 1e-5).all()


@pytest.mark.parametrize(
    ("extras", "columns"),
    [
        (ExtraInputs(), 0),
        (ExtraInputs(density=True), 1),
        (ExtraInputs(gradient=True), 3),
        (ExtraInputs(laplacian=True), 1),
        (ExtraInputs(True, True, False), 4),
        (ExtraInputs(True, True, True), 5),
    ],
)
def test_input_builder_columns(extras, columns):
    grid = _grid()
    x = grid.box.lo + grid.box.extent * torch.rand(20, 3, generator=torch.Generator().manual_seed(1))
    x[0] = grid.box.hi + 1.0  # outside: position clamped, extras zero
    d = torch.nn.functional.normalize(torch.randn(20, 3, generator=torch.Generator().manual_seed(2)), dim=1)
    for mode, n_dir in (("vector", 3), ("spherical", 2)):
        builder = InputBuilder(grid, mode, extras)
        raw = builder(x, d)
        assert raw.shape == (20, 3 + n_dir + columns) and builder.n_dims == raw.shape[1]
        torch.testing.assert_close(raw[:, :3], grid.box.normalize(x).clamp(0, 1))
        expected_dir = d if mode == "vector" else spherical_coordinates(d)
        torch.testing.assert_close(raw[:, 3:3 + n_dir], expected_dir)
        want = []
        if extras.density:
            want.append(grid.normalized_density(x)[:, None])
        if extras.gradient:
            want.append(grid.gradient(x))
        if extras.laplacian:
            want.append(grid.laplacian(x)[:, None])
        if want:
            torch.testing.assert_close(raw[:, 3 + n_dir:], torch.cat(want, dim=1))
            assert (raw[0, 3 + n_dir:] == 0).all()


def test_extras_are_identical_at_training_and_inference():
    grid = _grid()
    enc = {"position": {"otype": "TriangleWave", "n_frequencies": 4}, "direction": {"otype": "OneBlob", "n_bins": 4}}
    cache = build_radiance_cache(CACHE, enc, {"density": True, "gradient": True, "laplacian": True}, grid, "cpu", 0)
    seen = []
    hook = lambda module, args: seen.append(args[0].detach().clone())  # noqa: E731
    cache.network.register_forward_pre_hook(hook)
    cache.ema.shadow.register_forward_pre_hook(hook)
    x = grid.box.lo + grid.box.extent * torch.rand(40, 3, generator=torch.Generator().manual_seed(3))
    d = torch.nn.functional.normalize(torch.randn(40, 3, generator=torch.Generator().manual_seed(4)), dim=1)
    cache.train_step(x, d, torch.ones(40, 3))
    cache.query(x, d)
    assert len(seen) == 2
    torch.testing.assert_close(seen[0], seen[1], rtol=0, atol=0)
    torch.testing.assert_close(seen[1][:, 5], grid.normalized_density(x))
    assert seen[1][:, 5:].abs().sum() > 0


def _sun(direction, irradiance=1.0):
    from nrc.transport.lights import DirectionalLight

    return DirectionalLight(torch.tensor(direction, dtype=torch.float32), torch.full((3,), float(irradiance)))


def test_light_depth_column_grows_away_from_the_light_and_follows_it():
    from nrc.transport.lights import EnvironmentLight, PointLight
    from nrc.cache.inputs import key_light

    grid = DensityGrid(torch.ones(8, 8, 8), center=(0, 0, 0), diagonal=2.0, density_scale=20.0)
    extras = ExtraInputs(light_depth=True, light_depth_resolution=8)
    sky = EnvironmentLight(torch.ones(3), None)
    sun = _sun([-1.0, 0.0, 0.0])  # shines along -x: the +x side is lit
    dim_point = PointLight(torch.tensor([0.0, 5.0, 0.0]), torch.ones(3))
    assert key_light((sky, dim_point, sun), grid.box) is sun
    builder = InputBuilder(grid, "spherical", extras, (sky, sun))
    assert builder.n_dims == 6 and builder.column_blocks[-1] == (1, (False,))
    x = torch.tensor([[0.4, 0.0, 0.0], [0.0, 0.0, 0.0], [-0.4, 0.0, 0.0]])
    d = torch.tensor([[0.0, 1.0, 0.0]]).expand(3, 3)
    col = builder(x, d)[:, 5]
    assert bool((col[:-1] < col[1:]).all()) and bool(((col >= 0) & (col <= 1)).all())
    assert not builder.set_lights((sky, sun))  # the same light: nothing recomputed
    assert builder.set_lights((sky, _sun([1.0, 0.0, 0.0])))  # turned to the other side
    turned = builder(x, d)[:, 5]
    torch.testing.assert_close(turned, col.flip(0), rtol=1e-4, atol=1e-5)
    # no directional or point light: no column, whatever the key says
    assert InputBuilder(grid, "spherical", extras, (sky,)).n_dims == 5


def test_light_depth_cache_one_blob_encodes_the_column():
    grid = _grid()
    enc = {"position": {"otype": "TriangleWave", "n_frequencies": 4}, "direction": {"otype": "OneBlob", "n_bins": 4}}
    plain = build_radiance_cache(CACHE, enc, {}, grid, "cpu", 0, lights=(_sun([0.0, -1.0, 0.0]),))
    cache = build_radiance_cache(CACHE, enc, {"light_depth": True, "light_depth_bins": 8}, grid, "cpu", 0,
                                 lights=(_sun([0.0, -1.0, 0.0]),))
    assert cache.network.encoding.in_dim == plain.network.encoding.in_dim + 1
    assert cache.network.encoding.out_dim == plain.network.encoding.out_dim + 8
    x = grid.box.lo + grid.box.extent * torch.rand(16, 3, generator=torch.Generator().manual_seed(1))
    d = torch.nn.functional.normalize(torch.randn(16, 3, generator=torch.Generator().manual_seed(2)), dim=1)
    assert math.isfinite(cache.train_step(x, d, torch.ones(16, 3)))
    assert cache.query(x, d).shape == (16, 3)
    from nrc.errors import ConfigError
    with pytest.raises(ConfigError, match="light_depth_resolution"):
        build_radiance_cache(CACHE, enc, {"light_depth": True, "light_depth_resolution": 1}, grid, "cpu", 0)


def test_light_depth_resolution_auto_is_coarser_when_the_light_moves():
    from nrc.cache.inputs import LIGHT_DEPTH_CELLS, light_depth_cells
    from nrc.config import ConfigReader

    auto = ExtraInputs.from_config(ConfigReader({"light_depth": True, "light_depth_resolution": "auto"},
                                                "extra_inputs"))
    assert light_depth_cells(auto, False) == LIGHT_DEPTH_CELLS["static"] > light_depth_cells(auto, True)
    fixed = ExtraInputs(light_depth=True, light_depth_resolution=12)
    assert light_depth_cells(fixed, True) == 12
    grid = DensityGrid(torch.ones(64, 32, 16), center=(0, 0, 0), diagonal=2.0, density_scale=1.0)
    builder = InputBuilder(grid, "spherical", ExtraInputs(light_depth=True), (_sun([0.0, -1.0, 0.0]),), animated=True)
    assert builder.light_field._data.shape == (1, 1, 8, 16, 32)  # (1, C, z, y, x): 32 cells along x
    static = InputBuilder(grid, "spherical", ExtraInputs(light_depth=True), (_sun([0.0, -1.0, 0.0]),))
    assert static.light_field._data.shape == (1, 1, 16, 32, 64)
    small = DensityGrid(torch.ones(16, 8, 4), center=(0, 0, 0), diagonal=2.0, density_scale=1.0)
    capped = InputBuilder(small, "spherical", ExtraInputs(light_depth=True), (_sun([0.0, -1.0, 0.0]),))
    assert capped.light_field._data.shape == (1, 1, 4, 8, 16)  # never finer than the medium's own cells
