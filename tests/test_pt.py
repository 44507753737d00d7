"""Path tracer: analytic render-level checks, furnace test, determinism and hard cases."""

import re


import numpy as np
import pytest
import torch

from conftest import compose
from nrc.render.registry import make_renderer
from nrc.scene import load_scene
from nrc.volume.grid import DensityGrid


def make(overrides, density=None):
    """A PathTracer for a composed config; ``density`` replaces the grid (same placement keys)."""
    cfg = compose(["renderer=pt", "scene.volume.procedural.resolution=16", *overrides])
    scene = load_scene(cfg.scene)
    if density is not None:
        v = cfg.scene.volume
        grid = DensityGrid(density, tuple(v.center), v.diagonal, v.density_scale)
        scene = type(scene)(grid, scene.albedo, scene.g, scene.camera, scene.lights, scene.integrator)
    return make_renderer("pt", scene, cfg), scene


def pixel_transmittance(scene, n_jitter=256, n_steps=512):
    """Per-pixel mean transmittance of camera rays (jittered over the pixel), by midpoint quadrature."""
    cam, grid = scene.camera, scene.grid
    gen = torch.Generator().manual_seed(99)
    pix = torch.arange(cam.num_pixels).repeat_interleave(n_jitter)
    o, d = cam.generate_rays(pix, torch.rand(len(pix), 2, generator=gen))
    t0, t1 = grid.box.intersect(o, d)
    h = (t1 - t0) / n_steps
    tau = sum(grid.sigma_t(o + (t0 + (k + 0.5) * h)[:, None] * d) for k in range(n_steps)) * h
    return torch.exp(-tau).reshape(cam.num_pixels, n_jitter).mean(1).reshape(cam.height, cam.width).numpy()


SKY = ["scene=sky", "scene.camera.width=8", "scene.camera.height=6", "scene.camera.position=[0,0,120]",
       "scene.camera.look_at=[0,0,0]", "scene.camera.fov_y=50"]


def test_absorbing_medium_in_front_of_the_sky_gives_env_times_transmittance():
    gen = torch.Generator().manual_seed(0)
    density = torch.rand(10, 7, 5, generator=gen)
    density[8, 5, 1] = 6.0  # an off-centre hot voxel: an axis swap or flip would move it
    pt, scene = make(SKY + ["scene.volume.albedo=0", "scene.volume.density_scale=0.05",
                            "scene.integrator.spp=1024"], density)
    img = pt.render().image
    T = pixel_transmittance(scene)
    L = np.array([0.35, 0.5, 0.8], dtype=np.float32)
    want = T[..., None] * L
    se = L * np.sqrt(np.maximum(T * (1 - T), 1e-4) / 1024)[..., None]
    assert T.min() < 0.5 < T.max()  # the medium really attenuates some pixels and not others
    assert np.all(np.abs(img - want) < 4.5 * se + 1e-3)


@pytest.mark.parametrize("g", [0.0, 0.8])
def test_furnace_non_absorbing_medium_under_uniform_sky_is_invisible(g):
    """Albedo 1 under a uniform sky: every pixel equals the sky radiance (tests NEE + MIS + phase)."""
    pt, scene = make(SKY + ["scene.volume.albedo=1", "scene.volume.density_scale=0.08", f"scene.volume.g={g}",
                            "scene.integrator.max_scatter=400", "scene.integrator.spp=256"])
    img = pt.render().image
    L = np.array([0.35, 0.5, 0.8], dtype=np.float32)
    block_mean = img.reshape(-1, 3).mean(0)
    # per-pixel estimates are bounded and near L; the image mean is within a tight band
    np.testing.assert_allclose(block_mean, L, rtol=0.02)
    assert np.all(np.abs(img - L) < 0.15 * L)


def test_capped_survival_roulette_stops_albedo_one_paths_without_bias():
    """A survival cap below 1 (0.95: Mitsuba 3's rule) stops paths in a non-absorbing medium, where the throughput
    roulette alone never fires, and the furnace image stays the sky (weights 1/q keep it unbiased)."""
    base = SKY + ["scene.volume.albedo=1", "scene.volume.density_scale=0.6", "scene.volume.g=0.8",
                  "scene.integrator.max_scatter=2000", "scene.integrator.spp=256"]
    L = np.array([0.35, 0.5, 0.8], dtype=np.float32)
    rr = ["renderer.russian_roulette.enabled=true", "renderer.russian_roulette.start=2"]
    plain = make(base + rr)[0].render()  # q = max throughput = 1: never stops
    capped = make(base + rr + ["renderer.russian_roulette.max_survival=0.95"])[0].render()
    assert capped.metrics["tracking_steps"] < 0.9 * plain.metrics["tracking_steps"]
    for r in (plain, capped):
        assert np.isfinite(r.image).all()
        np.testing.assert_allclose(r.image.reshape(-1, 3).mean(0), L, rtol=0.03)


def test_same_seed_same_image_other_seed_other_image():
    base = ["scene.camera.width=10", "scene.camera.height=6", "scene.integrator.spp=2"]
    a = make(base)[0].render().image
    b = make(base)[0].render().image
    c = make(base + ["scene.integrator.seed=5"])[0].render().image
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_working_set_size_does_not_bias():
    """Refill and compaction bookkeeping: a tiny working set renders the same expectation."""
    base = SKY + ["scene.volume.albedo=0", "scene.integrator.spp=256", "scene.volume.density_scale=0.05"]
    a = make(base)[0].render().image
    b = make(base + ["renderer.slots=97", "renderer.shadow_batch=13"])[0].render().image
    np.testing.assert_allclose(a.mean(), b.mean(), rtol=0.03)


HARD = [
    ["scene.volume.g=-0.999"],
    ["scene.volume.g=0.999"],
    ["scene.volume.g=0.0"],
    ["scene.volume.density_scale=0"],
    pytest.param(["scene.volume.density_scale=10000", "scene.integrator.max_scatter=4"], marks=pytest.mark.slow),
    ["scene=point", "scene.camera.position=[0,-15,5]"],  # camera and point light inside the volume
    ["scene=sun_sky", "scene.camera.position=[50,50,120]", "scene.camera.look_at=[50,50,0]"],  # grazing the box
]


@pytest.mark.parametrize("overrides", HARD)
def test_hard_cases_stay_finite(overrides):
    pt, _ = make(["scene.camera.width=6", "scene.camera.height=4", "scene.integrator.spp=2",
                  "scene.integrator.max_scatter=16", *overrides])
    img = pt.render().image
    assert np.isfinite(img).all() and (img >= 0).all()


@pytest.mark.parametrize("kind", ["empty", pytest.param("spike", marks=pytest.mark.slow)])
def test_degenerate_grids_stay_finite(kind):
    density = torch.zeros(9, 9, 9)
    if kind == "spike":
        density[4, 4, 4] = 1000.0
    pt, _ = make(["scene=sun_sky", "scene.camera.width=6", "scene.camera.height=4", "scene.integrator.spp=4"],
                 density)
    img = pt.render().image
    assert np.isfinite(img).all()
    if kind == "empty":  # nothing scatters: the sky alone
        np.testing.assert_allclose(img, np.broadcast_to([0.35, 0.5, 0.8], img.shape), rtol=1e-6)


@pytest.mark.parametrize("renderer, bad, message", [
    ("pt", "+renderer.slotz=5", "renderer: unknown key(s) slotz"),
    ("pt", "renderer.russian_roulette.start=0", "renderer.russian_roulette.start must be >= 1"),
    ("pt", "renderer.free_flight=dda", "renderer.free_flight must be one of"),
    ("pt", "+renderer.russian_roulette.stat=3", "renderer.russian_roulette: unknown key(s) stat"),
    ("preview", "+renderer.chunks=5", "renderer: unknown key(s) chunks"),
    ("preview", "renderer.chunk=0", "renderer.chunk must be >= 1"),
])
def test_renderer_settings_reject_unknown_and_bad_keys(renderer, bad, message):
    """Typed settings (PathTracerSettings, PreviewSettings): a typo or a bad value is one error naming the key."""
    from nrc.errors import ConfigError
    from nrc.render.registry import make_renderer

    cfg = compose([f"renderer={renderer}", "scene.volume.procedural.resolution=16", bad])
    with pytest.raises(ConfigError, match=re.escape(message)):
        make_renderer(renderer, load_scene(cfg.scene), cfg)


def test_path_tracer_settings_come_from_the_yaml():
    """One home for each default: the YAML (the dataclass reads every key as required)."""
    from nrc.render.pt import PathTracerSettings

    st = PathTracerSettings.from_config(compose(["renderer=pt"]).renderer)
    assert (st.slots, st.backend, st.russian_roulette, st.rr_start) == (65536, "auto", False, 8)
    from nrc.errors import ConfigError

    with pytest.raises(ConfigError, match="renderer.slots is required"):
        PathTracerSettings.from_config({"name": "pt"})


THREE_LIGHTS = ["scene=sun_sky", "scene.volume.procedural.resolution=24", "scene.camera.width=16",
                "scene.camera.height=8", "scene.integrator.spp=16", "scene.volume.albedo=0.9",
                "scene.lights=[{type:directional,direction:[-0.6,-0.55,-0.35],irradiance:[2.6,2.5,2.3]},"
                "{type:point,position:[0,-45,10],intensity:[900,700,500]},"
                "{type:environment,radiance:[0.05,0.08,0.15],path:null,scale:1.0}]"]


@pytest.mark.slow
@pytest.mark.parametrize("structure", ["eager", "step"])
def test_power_light_selection_agrees_with_uniform(structure):
    """``renderer.light_selection=power`` changes only the noise: sun, point light and sky (selection
    probabilities 0.65, 0.10, 0.25 instead of 1/3 each), 8 renders each, on the eager step and on the compiled backend's step
    structure (ratio tracking inside the step, the per-slot light table) run eagerly."""
    from conftest import assert_images_agree

    def images(selection):
        out = []
        for seed in range(8):
            cfg = compose(["renderer=pt", *THREE_LIGHTS, f"renderer.light_selection={selection}",
                           f"scene.integrator.seed={seed}", "renderer.backend=eager"])
            tracer = make_renderer("pt", load_scene(cfg.scene), cfg)
            if structure == "step":
                tracer.core.backend, tracer.core.eager_step = "eager", tracer.core.step
            out.append(tracer.render().image)
        return out

    power = images("power")
    assert_images_agree(power, images("uniform"))
    cfg = compose(["renderer=pt", *THREE_LIGHTS, "renderer.light_selection=power"])
    pmf = make_renderer("pt", load_scene(cfg.scene), cfg).lights.pmf
    assert pmf[0] > pmf[2] > pmf[1] > 0 and abs(sum(pmf) - 1) < 1e-6  # sun (0.65), sky (0.25), point light (0.10)
