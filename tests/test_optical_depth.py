"""Optical depth along the camera rays (nrc/volume/optical_depth.py) against hand-computed grids."""

import types

import pytest
import torch

from nrc.camera import Camera
from nrc.volume.grid import DensityGrid
from nrc.volume.optical_depth import camera_optical_depths, scene_optical_depth


def _camera(position, look_at, width=1, height=1, fov=10.0):
    t = lambda v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    return Camera.look_at(t(position), t(look_at), t([0.0, 1.0, 0.0]), fov, width, height)


def _grid(values, scale=2.0):
    values = torch.as_tensor(values, dtype=torch.float32)
    nx, ny, nz = values.shape
    diagonal = (nx * nx + ny * ny + nz * nz) ** 0.5  # voxel edge 1 world unit, box centred at the origin
    return DensityGrid(values, [0.0, 0.0, 0.0], diagonal, scale)


def test_axis_ray_is_the_column_sum():
    # 3 x 3 x 7 grid; the camera on the +z axis looks down -z through the centre column (i, j) = (1, 1).
    # The clamped trilinear field along a cell-centre line integrates to sum_k v_k x voxel exactly.
    g = torch.Generator().manual_seed(3)
    v = torch.rand((3, 3, 7), generator=g)
    grid = _grid(v, scale=2.0)
    tau = camera_optical_depths(_camera([0, 0, 50], [0, 0, 0]), grid)
    assert tau.shape == (1,)
    assert float(tau[0]) == pytest.approx(2.0 * float(v[1, 1].sum()), rel=1e-4)


def test_oblique_constant_medium_is_sigma_times_chord():
    grid = _grid(torch.ones((8, 8, 8)), scale=0.5)
    cam = _camera([30.0, 20.0, 40.0], [0.3, -0.2, 0.1], width=5, height=4, fov=6.0)
    tau = camera_optical_depths(cam, grid, steps_per_voxel=1.0)
    pix = torch.arange(cam.num_pixels)
    o, d = cam.generate_rays(pix, torch.full((len(pix), 2), 0.5))
    t0, t1 = grid.box.intersect(o, d)
    chord = (t1 - t0.clamp(min=0)).clamp(min=0)
    assert bool((chord > 0).all())
    torch.testing.assert_close(tau, 0.5 * chord, rtol=1e-4, atol=1e-5)


def test_rays_that_miss_have_zero_and_stats_count_only_the_medium():
    v = torch.zeros((5, 5, 5))
    v[2, 2, :] = 1.0  # one column of medium: only rays near the axis meet it
    grid = _grid(v, scale=4.0)
    cam = _camera([0, 0, 30], [0, 0, 0], width=9, height=9, fov=20.0)
    tau = camera_optical_depths(cam, grid)
    assert float(tau[40]) == pytest.approx(4.0 * 5.0, rel=1e-4)  # the centre pixel runs along the column
    assert float(tau[0]) == 0.0  # a corner pixel misses the box or the column
    scene = types.SimpleNamespace(camera=cam, grid=grid, g=0.75)
    od = scene_optical_depth(scene)
    seen = tau[tau > 0].double()
    assert od.medium_pixels == int((tau > 0).sum()) and od.pixels == 81
    assert od.median == pytest.approx(float(seen.quantile(0.5)))
    assert od.median_reduced == pytest.approx(0.25 * od.median)
    assert od.p10 <= od.median <= od.p90


def test_empty_medium():
    grid = _grid(torch.zeros((4, 4, 4)))
    od = scene_optical_depth(types.SimpleNamespace(camera=_camera([0, 0, 20], [0, 0, 0], 3, 2), grid=grid, g=0.0))
    assert (od.median, od.medium_pixels, od.pixels) == (0.0, 0, 6)


def test_light_field_of_a_constant_medium_is_sigma_times_the_distance_to_the_light():
    from nrc.volume.optical_depth import axis_chord_depth, light_optical_depth_field

    grid = _grid(torch.ones((8, 4, 6)), scale=0.5)  # voxel edge 1, box [-4, 4] x [-2, 2] x [-3, 3]
    # a sun shining along -x: every cell looks towards +x, to the face at x = 4 (field cells 1 voxel: exact)
    tau = light_optical_depth_field(grid, direction=torch.tensor([-2.0, 0.0, 0.0]), resolution=8,
                                    steps_per_voxel=1.0)
    assert tau.shape == (8, 4, 6)
    expected = 0.5 * (4.0 - (torch.arange(8) + 0.5 - 4.0))
    torch.testing.assert_close(tau[:, 1, 2], expected, rtol=1e-4, atol=1e-5)
    # a point light inside the box: the depth to the light, not to the box's exit
    tau = light_optical_depth_field(grid, position=torch.tensor([0.5, 0.5, 0.5]), resolution=8, steps_per_voxel=2.0)
    assert float(tau[4, 2, 3]) == pytest.approx(0.0, abs=1e-6)  # the light's own cell
    assert float(tau[0, 2, 3]) == pytest.approx(0.5 * 4.0, rel=1e-3)  # the cell at x = -3.5: 4 units away
    assert axis_chord_depth(grid) == pytest.approx(0.5 * 8.0)
    with pytest.raises(ValueError, match="exactly one"):
        light_optical_depth_field(grid)


def test_a_kept_light_field_is_read_back_for_the_same_medium_and_light_and_made_anew_otherwise(tmp_path, monkeypatch):
    """``keep=True``: the field is marched once and read from disk the next time (the same values, bitwise); another
    density scale, grid value or light direction is another entry."""
    from nrc.volume import optical_depth as od_module
    from nrc.volume.optical_depth import light_optical_depth_field

    monkeypatch.setenv("NRC_CACHE_DIR", str(tmp_path))
    marched = []
    march = od_module._midpoint_depth
    monkeypatch.setattr(od_module, "_midpoint_depth", lambda *a: marched.append(1) or march(*a))
    g = torch.rand((6, 5, 4), generator=torch.Generator().manual_seed(3))
    sun = torch.tensor([0.3, -1.0, 0.2])
    first = light_optical_depth_field(_grid(g), direction=sun, resolution=6, keep=True)
    n = len(marched)
    assert n > 0 and len(list((tmp_path / "light_depth").glob("*.npy"))) == 1
    again = light_optical_depth_field(_grid(g.clone()), direction=sun.clone(), resolution=6, keep=True)
    assert len(marched) == n  # read back, not marched
    assert torch.equal(again, first) and torch.equal(first, light_optical_depth_field(_grid(g), direction=sun,
                                                                                      resolution=6))
    g2 = g.clone()
    g2[2, 2, 2] += 1.0
    for grid, light in ((_grid(g, scale=3.0), sun), (_grid(g2), sun), (_grid(g), torch.tensor([0.0, -1.0, 0.0]))):
        light_optical_depth_field(grid, direction=light, resolution=6, keep=True)
    assert len(list((tmp_path / "light_depth").glob("*.npy"))) == 4
