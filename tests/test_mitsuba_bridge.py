"""The Mitsuba 3 bridge reproduces the SCENE.md conventions (skipped without Mitsuba).

Unit checks compare the Mitsuba objects built by :func:`to_mitsuba_dict` with ours directly (grid lookups,
camera rays, light samples, environment lookups); render checks compare Mitsuba images with quadrature.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")

from nrc.camera import Camera  # noqa: E402
from nrc.evaluation.mitsuba_bridge import (  # noqa: E402
    latlong_lookup,
    mitsuba_available,
    render_mitsuba,
    to_mitsuba_dict,
)
from nrc.scene import Integrator, Scene  # noqa: E402
from nrc.transport.lights import DirectionalLight, EnvironmentLight, PointLight  # noqa: E402
from nrc.volume import DensityGrid  # noqa: E402

pytestmark = pytest.mark.mitsuba

VARIANT = "scalar_rgb"
ENV_RGB = [0.5, 1.0, 2.0]
CENTER = (0.3, -0.2, 0.1)


@pytest.fixture(autouse=True)
def _variant():
    """Every test here starts in ``VARIANT`` (a process-wide setting: under xdist a test may follow one that
    switched Mitsuba to another variant, or come first in its worker)."""
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)


def _t(v) -> torch.Tensor:
    return torch.tensor(v, dtype=torch.float32)


def _scene(density, center, diagonal, scale, camera, lights, albedo=0.0, g=0.0, max_scatter=2, spp=16):
    grid = DensityGrid(torch.as_tensor(density, dtype=torch.float32), center, diagonal, scale)
    return Scene(grid, albedo, g, camera, tuple(lights), Integrator(max_scatter, spp, 0))


def _asymmetric_density() -> np.ndarray:
    """12 x 7 x 5 grid: a smooth ramp plus one hot voxel near the (+x, +y, -z) corner."""
    i, j, k = np.meshgrid(np.arange(12), np.arange(7), np.arange(5), indexing="ij")
    d = 0.15 + 0.05 * i / 11 + 0.1 * (j / 6) ** 2 + 0.03 * k
    d[10, 5, 1] = 6.0
    d[2, 1, 3] = 2.5
    return d.astype(np.float32)


def _asymmetric_scene(density=None, center=CENTER, width=40, height=24, spp=16) -> Scene:
    d = _asymmetric_density() if density is None else density
    diagonal = 0.25 * math.sqrt(12**2 + 7**2 + 5**2)  # voxel size 0.25: box 3 x 1.75 x 1.25
    cam = Camera.look_at(_t([3.4, 2.6, 3.9]), _t(list(CENTER)), _t([0.0, 1.0, 0.0]), 26.0, width, height)
    env = EnvironmentLight(_t([2.0 * c for c in ENV_RGB]), None, 0.5)  # radiance x scale = ENV_RGB
    return _scene(d, list(center), diagonal, 1.2, cam, [env], albedo=0.0, spp=spp)


def _pixel_transmittance(scene: Scene, n_jitter: int = 4, n_steps: int = 96) -> np.ndarray:
    """(H, W) pixel-averaged transmittance through the medium: ``n_jitter^2`` stratified rays per pixel,
    midpoint quadrature of ``sigma_t`` between the box entry and exit."""
    cam, grid = scene.camera, scene.grid
    n_pix = cam.num_pixels
    s = (torch.arange(n_jitter, dtype=torch.float64) + 0.5) / n_jitter
    jx, jy = torch.meshgrid(s, s, indexing="xy")
    jit = torch.stack([jx.reshape(-1), jy.reshape(-1)], dim=-1).float()
    total = torch.zeros(n_pix, dtype=torch.float64)
    pix = torch.arange(n_pix)
    for jj in jit:
        o, d = cam.generate_rays(pix, jj.expand(n_pix, 2))
        t0, t1 = grid.box.intersect(o, d)
        u = (torch.arange(n_steps, dtype=torch.float32) + 0.5) / n_steps
        t = t0[:, None] + (t1 - t0)[:, None] * u[None]
        x = o[:, None] + t[..., None] * d[:, None]
        tau = grid.sigma_t(x.reshape(-1, 3)).view(n_pix, n_steps).double().sum(1) * (t1 - t0).double() / n_steps
        total += torch.exp(-tau)
    return (total / len(jit)).view(cam.height, cam.width).numpy()


def _z_scores(measured: np.ndarray, reference: np.ndarray, spp: int) -> np.ndarray:
    """Per-pixel z-scores of an albedo-0 render (each sample is 0 or 1 in units of L_env)."""
    var = np.maximum(reference * (1.0 - reference), 1e-3) / spp
    return (measured - reference) / np.sqrt(var)


# ---------------------------------------------------------------------------- unit checks
def test_available():
    assert mitsuba_available()


def test_grid_lookup_matches_ours():
    """gridvolume (data[z][y][x], cell-centred, clamped) through the dict's to_world equals DensityGrid.lookup."""
    scene = _asymmetric_scene()
    d = to_mitsuba_dict(scene, variant=VARIANT)
    vol = mi.load_dict(d["cloud"]["sigma_t"])
    grid = scene.grid
    lo, hi = grid.box.lo.numpy().astype(np.float64), grid.box.hi.numpy().astype(np.float64)
    rng = np.random.default_rng(0)
    pts = lo + (hi - lo) * rng.uniform(0.0, 1.0, size=(1500, 3))
    # include points within half a cell of the faces and exactly at cell centres
    pts[:200] = lo + (hi - lo) * rng.choice([0.0, 0.01, 0.99, 1.0], size=(200, 3))
    ours = grid.lookup(torch.tensor(pts, dtype=torch.float32)).numpy()
    theirs = np.empty(len(pts))
    for n, p in enumerate(pts):
        it = mi.Interaction3f()
        it.p = mi.Point3f(*p)
        theirs[n] = vol.eval_1(it)
    np.testing.assert_allclose(theirs, ours, atol=2e-5)


def test_camera_rays_match_ours():
    """Mitsuba's sensor rays through film position (col + jx, row + jy) / (W, H) are our camera's rays."""
    scene = _asymmetric_scene(width=9, height=5)
    sensor = mi.load_dict(to_mitsuba_dict(scene, variant=VARIANT)["sensor"])
    cam = scene.camera
    rng = np.random.default_rng(1)
    pix = torch.arange(cam.num_pixels)
    jit = torch.tensor(rng.random((cam.num_pixels, 2)), dtype=torch.float32)
    _, ours = cam.generate_rays(pix, jit)
    for k in range(cam.num_pixels):
        row, col = divmod(k, cam.width)
        film = mi.Point2f((col + float(jit[k, 0])) / cam.width, (row + float(jit[k, 1])) / cam.height)
        ray, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
        np.testing.assert_allclose(np.array(ray.d), ours[k].numpy(), atol=2e-6)


def test_light_conventions():
    """directional `direction` is the propagation direction; point weight = intensity / r^2."""
    cam = Camera.look_at(_t([0, 0, 5]), _t([0, 0, 0]), _t([0, 1, 0]), 30.0, 4, 4)
    sun_dir = np.array([-0.6, -0.55, -0.35])
    sun_dir /= np.linalg.norm(sun_dir)
    lights = [
        DirectionalLight(_t(sun_dir), _t([2.6, 2.5, 2.3])),
        PointLight(_t([1.0, 2.0, -2.0]), _t([9.0, 18.0, 27.0])),
    ]
    d = to_mitsuba_dict(_scene(np.ones((2, 2, 2)), [0, 0, 0], 1.0, 1.0, cam, lights), variant=VARIANT)
    it = mi.Interaction3f()
    it.p = mi.Point3f(0.0, 0.0, 0.0)
    sun = mi.load_dict(d["sun_0"])
    ds, w = sun.sample_direction(it, mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(np.array(ds.d), -sun_dir, atol=1e-6)  # towards the light
    np.testing.assert_allclose(np.array(w), [2.6, 2.5, 2.3], rtol=1e-6)
    point = mi.load_dict(d["point_0"])
    ds, w = point.sample_direction(it, mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(np.array(ds.d), np.array([1.0, 2.0, -2.0]) / 3.0, atol=1e-6)
    np.testing.assert_allclose(np.array(w), np.array([9.0, 18.0, 27.0]) / 9.0, rtol=1e-5)


def test_hg_forward_for_positive_g():
    """Mitsuba's hg with g > 0 peaks for the continuing direction (its wi points back along the path)."""
    phase = mi.load_dict({"type": "hg", "g": 0.8})
    mei = mi.MediumInteraction3f()
    mei.wi = mi.Vector3f(0.0, 0.0, 1.0)  # the path arrived travelling along -z
    mei.sh_frame = mi.Frame3f(mei.wi)
    ctx = mi.PhaseFunctionContext(None)
    fwd = phase.eval_pdf(ctx, mei, mi.Vector3f(0.0, 0.0, -1.0))[1]
    hg = lambda cos: (1 - 0.64) / (4 * math.pi * (1 + 0.64 - 1.6 * cos) ** 1.5)  # noqa: E731
    assert fwd == pytest.approx(hg(1.0), rel=1e-5)


def test_environment_image_mapping():
    """The envmap built from a lat-long image evaluates exactly as latlong_lookup (SCENE.md mapping) x scale."""
    rng = np.random.default_rng(2)
    image = rng.random((6, 10, 3)).astype(np.float32)
    cam = Camera.look_at(_t([0, 0, 5]), _t([0, 0, 0]), _t([0, 1, 0]), 30.0, 4, 4)
    env = EnvironmentLight(None, torch.from_numpy(image), 1.7)
    d = to_mitsuba_dict(_scene(np.ones((2, 2, 2)), [0, 0, 0], 1.0, 1.0, cam, [env]), variant=VARIANT)
    emitter = mi.load_dict(d["environment"])
    dirs = rng.normal(size=(800, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs[:2] = [[0, 0, -1], [1, 0, 0]]  # column 0 (-z) and a quarter turn (+x); the exact poles have no azimuth
    theirs = np.empty((len(dirs), 3))
    for n, dd in enumerate(dirs):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-dd))  # Mitsuba looks up -wi
        theirs[n] = np.array(emitter.eval(si))
    np.testing.assert_allclose(theirs, 1.7 * latlong_lookup(image, dirs), atol=2e-5)
    # the reference itself: -z (u = 0, v = 1/2) lies between the last and first column and rows 2 and 3;
    # a quarter turn (+x, u = 1/4) is the centre of column 2 (of 10)
    ref = latlong_lookup(image, np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(ref[0], 0.25 * (image[2, -1] + image[2, 0] + image[3, -1] + image[3, 0]), atol=1e-6)
    np.testing.assert_allclose(ref[1], 0.5 * (image[2, 2] + image[3, 2]), atol=1e-6)


# ---------------------------------------------------------------------------- renders
def test_albedo0_transmittance_matches_quadrature():
    """Albedo-0 medium in front of a uniform sky: pixel = L_env * T (pixel-averaged), for every pixel.

    Each Mitsuba sample is exactly 0 or L_env, so with the reference T a pixel's mean has standard deviation
    sqrt(T (1 - T) / spp); all |z| must be < 5.5 (40 x 24 pixels). The same statistic rejects the usual
    mistakes (reshaping D instead of transposing it, a half-cell offset along any axis, a mirrored or flipped
    image) with max |z| > 10, checked below. The reference (4 x 4 stratified rays per pixel, 96-step midpoint
    quadrature) is within ~1e-3 of a 12 x 12 x 512 one, far below the Monte Carlo noise (<= 0.022).
    """
    spp = 512
    scene = _asymmetric_scene(spp=spp)
    image, _ = render_mitsuba(scene, variant=VARIANT, threads=2)
    assert image.shape == (24, 40, 3) and image.dtype == np.float32
    measured = image / np.asarray(ENV_RGB, dtype=np.float32)
    # the three channels come from the same binary paths
    np.testing.assert_allclose(measured[..., 0], measured[..., 2], atol=1e-5)
    np.testing.assert_allclose(measured[..., 0], measured[..., 1], atol=1e-5)
    m = measured[..., 1].astype(np.float64)
    ref = _pixel_transmittance(scene)
    assert ref.min() < 0.3 and ref.max() == pytest.approx(1.0)  # the hot voxel is visible, sky around
    z = _z_scores(m, ref, spp)
    assert np.abs(z).max() < 5.5, f"max |z| = {np.abs(z).max():.2f}"
    # no bias: the mean error over the pixels that see the medium is within 4 standard deviations
    seen = ref < 0.999
    bias_sd = math.sqrt((ref[seen] * (1 - ref[seen])).sum() / spp) / seen.sum()
    assert abs((m - ref)[seen].mean()) < 4 * bias_sd, ((m - ref)[seen].mean(), bias_sd)

    # the test discriminates: each wrong convention gives a far worse fit
    d = _asymmetric_density()
    wrong_order = d.ravel().reshape(d.shape[::-1]).transpose(2, 1, 0)  # reshaped, not transposed, to data[z][y][x]
    voxel = scene.grid.voxel_size
    wrong = {
        "memory order": _pixel_transmittance(_asymmetric_scene(density=np.ascontiguousarray(wrong_order))),
        **{
            f"half-cell {axis} offset": _pixel_transmittance(_asymmetric_scene(center=tuple(np.add(CENTER, shift))))
            for axis, shift in zip("xyz", 0.5 * voxel * np.eye(3))
        },
        "mirrored image": ref[:, ::-1],
        "flipped image": ref[::-1, :],
    }
    for name, r in wrong.items():
        zw = np.abs(_z_scores(m, r, spp)).max()
        assert zw > 10.0, f"{name}: max |z| only {zw:.2f}"


def test_dense_voxel_at_plus_x_is_on_the_right():
    """A dense column at +x of the box is dark on the right of the image seen from +z (left from -z);
    a dense slab at +y is dark at the top (row 0)."""
    d = np.zeros((8, 8, 8), dtype=np.float32)
    d[6:, 2:6, 2:6] = 20.0
    env = EnvironmentLight(_t([1.0, 1.0, 1.0]), None, 1.0)
    for z, sign in ((4.0, 1), (-4.0, -1)):
        cam = Camera.look_at(_t([0, 0, z]), _t([0, 0, 0]), _t([0, 1, 0]), 30.0, 16, 12)
        img, _ = render_mitsuba(_scene(d, [0, 0, 0], math.sqrt(3) * 2, 1.0, cam, [env]), spp=8, variant=VARIANT)
        lum = img.mean(-1)
        left, right = lum[:, :8].mean(), lum[:, 8:].mean()
        dark, bright = (right, left) if sign > 0 else (left, right)
        assert dark < 0.8 * bright, (z, left, right)
    d = np.zeros((8, 8, 8), dtype=np.float32)
    d[:, 6:, :] = 20.0
    cam = Camera.look_at(_t([0, 0, 4.0]), _t([0, 0, 0]), _t([0, 1, 0]), 30.0, 16, 12)
    img, _ = render_mitsuba(_scene(d, [0, 0, 0], math.sqrt(3) * 2, 1.0, cam, [env]), spp=8, variant=VARIANT)
    lum = img.mean(-1)
    assert lum[:6].mean() < 0.8 * lum[6:].mean()


@pytest.mark.parametrize(
    "direction, lit", [([-1.0, 0.0, 0.0], "right"), ([1.0, 0.0, 0.0], "left"), ([0.0, -1.0, 0.0], "top")]
)
def test_directional_light_lights_the_near_side(direction, lit):
    """Sun only, albedo 1, uniform optically thick cube seen from +z: the side the light comes from is
    brighter; rays that miss the box see black (no environment)."""
    d = np.ones((6, 6, 6), dtype=np.float32)
    cam = Camera.look_at(_t([0, 0, 5.0]), _t([0, 0, 0]), _t([0, 1, 0]), 36.0, 20, 20)
    sun = DirectionalLight(_t(direction), _t([3.0, 3.0, 3.0]))
    scene = _scene(d, [0, 0, 0], math.sqrt(3) * 2, 4.0, cam, [sun], albedo=1.0, g=0.0, max_scatter=4, spp=16)
    img, _ = render_mitsuba(scene, variant=VARIANT)
    lum = img.mean(-1)
    assert np.isfinite(img).all() and img.min() > -1e-6  # float round-off only
    half = {"right": lum[:, 10:], "left": lum[:, :10], "top": lum[:10]}[lit].mean()
    other = {"right": lum[:, :10], "left": lum[:, 10:], "top": lum[10:]}[lit].mean()
    assert half > 1.5 * other > 0, (half, other)
    # the box (edge 2 at distance 4..6, fov 36 deg) covers the centre, not the corner pixels
    assert img[0, 0].max() == 0.0 and img[-1, -1].max() == 0.0


def test_camera_inside_the_medium():
    """A camera inside the box starts in the medium: uniform D, albedo 0, sky L: pixel = L exp(-sigma_t t_exit)."""
    cam = Camera.look_at(_t([0.1, -0.2, 0.3]), _t([0.5, 0.0, -2.0]), _t([0, 1, 0]), 60.0, 8, 6)
    env = EnvironmentLight(_t([1.0, 1.0, 1.0]), None, 1.0)
    spp = 256
    scene = _scene(np.ones((4, 4, 4)), [0, 0, 0], 2 * math.sqrt(3), 0.7, cam, [env], spp=spp)
    assert "medium" in to_mitsuba_dict(scene, variant=VARIANT)["sensor"]
    img, _ = render_mitsuba(scene, variant=VARIANT)
    pix = torch.arange(cam.num_pixels)
    s = (torch.arange(4, dtype=torch.float32) + 0.5) / 4
    jit = torch.stack(torch.meshgrid(s, s, indexing="xy"), -1).reshape(-1, 2)
    ref = np.zeros(cam.num_pixels)
    for jj in jit:
        o, d = cam.generate_rays(pix, jj.expand(cam.num_pixels, 2))
        _, t_exit = scene.grid.box.intersect(o, d)
        ref += np.exp(-0.7 * t_exit.double().numpy()) / len(jit)
    ref = ref.reshape(cam.height, cam.width)
    assert ref.max() < 0.6  # every pixel looks through the medium
    assert np.abs(_z_scores(img[..., 0].astype(np.float64), ref, spp)).max() < 5.5
