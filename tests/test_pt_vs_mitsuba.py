"""The path tracer agrees with Mitsuba 3 (an independent renderer) pixel-block-wise within Monte Carlo error."""

import numpy as np
import pytest

from conftest import assert_images_agree, compose, hollow_lantern
from nrc.render.pt import PathTracer
from nrc.render.registry import make_renderer
from nrc.scene import load_scene

mitsuba_bridge = pytest.importorskip("nrc.evaluation.mitsuba_bridge")
if not mitsuba_bridge.mitsuba_available():
    pytest.skip("Mitsuba 3 is not installed (pip install mitsuba==3.9.1)", allow_module_level=True)

pytestmark = [pytest.mark.mitsuba, pytest.mark.slow]

SEEDS = 4  # independent renders per side: the standard errors come from their spread


# A point light inside the medium makes next-event estimation heavy-tailed (the 1/r^2 of vertices next to
# the light has infinite variance), so image means converge too slowly for a test: the light sits outside.
CASES = {"sun_sky": [], "point": ["scene.lights.0.position=[30,70,40]"]}


@pytest.mark.parametrize("preset", list(CASES))
def test_pt_matches_mitsuba(preset):
    compare_with_mitsuba(CASES[preset], preset)


# Light sampling modes (docs/path_tracer.md, "Light selection", "Point lights"): every mode is unbiased, so each
# agrees with Mitsuba's own next-event estimation on sun + sky, on the many-lights preset and on a point light
# inside the cloud (in a pocket of clear air, conftest.hollow_lantern, so that Mitsuba's estimate converges too).
MODES = {
    "sun_sky-power": (["renderer.light_selection=power"], "sun_sky"),
    "sun_sky-ris": (["renderer.light_selection=ris", "renderer.ris.candidates=4"], "sun_sky"),
    "many_lights-uniform": (["renderer.light_selection=uniform"], "many_lights"),
    "many_lights-ris": (["renderer.light_selection=ris"], "many_lights"),
    "many_lights-ris-equiangular": (["renderer.light_selection=ris", "renderer.point_light_sampling=equiangular"],
                                    "many_lights"),
}


@pytest.mark.parametrize("case", list(MODES))
def test_light_sampling_modes_match_mitsuba(case):
    """(Mitsuba picks one of the 17 lights uniformly: at 256 spp its image mean on many_lights still scatters
    by +-7 % between seeds, so that preset runs 1024.)"""
    extra, preset = MODES[case]
    compare_with_mitsuba(extra, preset, spp=1024 if preset == "many_lights" else 256)


@pytest.mark.parametrize("mode", ["none", "equiangular"])
def test_point_light_inside_the_cloud_matches_mitsuba(tmp_path, mode):
    scene = hollow_lantern(tmp_path)
    compare_with_mitsuba([*scene[1:], f"renderer.point_light_sampling={mode}", "scene.volume.density_scale=0.08"],
                         "lantern", spp=1024)


def test_pt_matches_mitsuba_under_a_latlong_environment(tmp_path):
    """Environment-map importance sampling and MIS against Mitsuba's envmap emitter."""
    from nrc.io import write_exr

    h, w = 16, 32
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    sky = np.stack(np.broadcast_arrays(0.2 + 0.6 * (1 - v)[:, None], 0.3 + 0.5 * (1 - v)[:, None],
                                       0.5 + 0.4 * (1 - v)[:, None] + 0 * u[None]), -1).astype(np.float32)
    sky[2:4, 20:22] = 60.0  # a small bright sun up high, about a quarter turn from -z towards +x
    write_exr(tmp_path / "env.exr", sky)
    compare_with_mitsuba(["scene.lights.0.radiance=null", f"scene.lights.0.path={tmp_path / 'env.exr'}"], "sky")


def test_pt_matches_mitsuba_on_the_default_scene():
    """The default scene as it ships (the cumulus, back-lit sun and sky, g 0.8, albedo 1), on a coarser grid
    and with at most 6 scattering events (the same truncation on both sides)."""
    compare_with_mitsuba([], "sun", medium=[])


def compare_with_mitsuba(extra: list[str], preset: str, render=lambda tracer: tracer.render(),
                         seeds: int = SEEDS, medium: list[str] | None = None, spp: int = 256) -> None:
    """``render(PathTracer)`` against Mitsuba on a small scene, over ``seeds`` independent renders of each (the
    standard errors come from their spread: Welch's t with about ``2 seeds - 2`` degrees of freedom).
    ``medium`` replaces the default ``g 0.6, albedo 0.9`` (``[]``: the preset's own)."""
    medium = ["scene.volume.g=0.6", "scene.volume.albedo=0.9"] if medium is None else medium
    overrides = [
        "renderer=pt", f"scene={preset}", *extra, "scene.volume.procedural.resolution=24",
        "scene.camera.width=16", "scene.camera.height=8", f"scene.integrator.spp={spp}",
        "scene.integrator.max_scatter=6", *medium,
    ]
    ours, theirs = [], []
    for seed in range(seeds):
        cfg = compose([*overrides, f"scene.integrator.seed={seed}"])
        scene = load_scene(cfg.scene)
        ours.append(render(make_renderer("pt", scene, cfg)).image)
        theirs.append(mitsuba_bridge.render_mitsuba(scene, seed=seed)[0])
    assert_images_agree(ours, theirs)
    mean_a, mean_b = (np.mean([im.mean() for im in ims]) for ims in (ours, theirs))
    assert abs(mean_a / mean_b - 1) < 0.1
