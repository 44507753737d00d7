"""The transport core's compiled structure (ratio-tracking shadow rays inside the step), run eagerly, against the
eager backend and Mitsuba 3; its component-form building blocks at their owners (trilinear lookup in
``volume/grid.py``, box exit in ``volume/box.py``, HG sampling in ``transport/phase.py``, the light table in
``transport/light_sampling.py``) against the batched forms; one real compile shared by two scenes."""

import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import REPO, hard_rays, spike_grid, unit
from test_architecture import imports
from test_pt import make
from nrc.errors import ConfigError
from nrc.transport.light_sampling import LightSampler, LightTable
from nrc.transport.lights import PointLight
from nrc.transport.phase import hg_sample, hg_sample_v3
from nrc.transport.rng import hash32, path_key, uniforms
from nrc.volume.box import box_exit
from nrc.volume.grid import DensityGrid, trilinear


def render_sm(pt):
    """Render with the compiled backend's step structure run eagerly (the code the compiled backend compiles)."""
    pt.core.backend = "eager"
    pt.core.eager_step = pt.core.step
    return pt.render()


def v3(x):
    return tuple(x.unbind(1))


def box_of(grid):
    return tuple(grid.box.lo.tolist()), tuple(grid.box.hi.tolist())


# ---------------------------------------------------------------------------------------------- building blocks
@pytest.mark.parametrize("kind", ["random", "spike", "thin"])
def test_trilinear_matches_grid_lookup(kind):
    gen = torch.Generator().manual_seed(3)
    if kind == "spike":
        grid = spike_grid()
    elif kind == "thin":  # a single cell along one axis: clamping on both sides
        grid = DensityGrid(torch.rand(5, 1, 3, generator=gen), (0.3, 0.1, -0.2), 2.0, 1.5)
    else:
        grid = DensityGrid(torch.rand(7, 5, 9, generator=gen), (0.3, 0.1, -0.2), 4.0, 1.0)
    lo, hi = grid.box.lo, grid.box.hi
    ext = hi - lo
    x = lo - 0.1 * ext + 1.2 * ext * torch.rand(20000, 3, generator=gen)  # inside, near faces and outside
    faces = lo + ext * torch.rand(300, 3, generator=gen)
    faces[:100, 0], faces[100:200, 1], faces[200:, 2] = lo[0], hi[1], hi[2]  # exactly on faces
    x = torch.cat([x, faces])
    got = trilinear(grid.density.reshape(-1), grid.shape, *box_of(grid), v3(x))
    np.testing.assert_allclose(got.numpy(), grid.lookup(x).numpy(), rtol=1e-5, atol=1e-6 * grid.max_density)
    bad = torch.tensor([[math.nan, 0.0, 0.0], [math.inf, 0.0, 0.0], [0.0, -math.inf, 0.0]])
    assert torch.equal(trilinear(grid.density.reshape(-1), grid.shape, *box_of(grid), v3(bad)), torch.zeros(3))
    # shape and box as 0-d tensors (how the compiled step passes them): the same values
    as_t = lambda v: tuple(torch.tensor(float(a)) for a in v)  # noqa: E731
    lo, hi = box_of(grid)
    got_t = trilinear(grid.density.reshape(-1), as_t(grid.shape), as_t(lo), as_t(hi), v3(x))
    assert torch.equal(got_t, got)


def test_box_exit_and_hg_sampling_match_the_eager_code():
    grid = spike_grid()
    o, d = hard_rays(grid)
    np.testing.assert_array_equal(box_exit(*box_of(grid), v3(o), v3(d)).numpy(), grid.box.intersect(o, d)[1].numpy())
    gen = torch.Generator().manual_seed(1)
    dirs = unit(torch.randn(4000, 3, generator=gen))
    dirs[:3] = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    u = torch.rand(4000, 2, generator=gen)
    for g in (-0.999, 0.0, 0.8):
        want, pdf_want = hg_sample(g, dirs, u)
        got, pdf = hg_sample_v3(torch.tensor(g), v3(dirs), u[:, 0], u[:, 1])
        np.testing.assert_allclose(torch.stack(got, 1).numpy(), want.numpy(), atol=1e-6)
        np.testing.assert_allclose(pdf.numpy(), pdf_want.numpy(), rtol=1e-6)


@pytest.mark.parametrize("preset", ["sun", "point", "sky", "sun_sky", "all"])
def test_component_light_sampler_matches_light_sampler(preset):
    _, scene = make([f"scene={'sun_sky' if preset == 'all' else preset}"])
    lights = scene.lights
    if preset == "all":  # three lights: the choice between them
        lights = lights + (PointLight(torch.tensor([10.0, 60.0, 5.0]), torch.tensor([5.0, 6.0, 7.0])),)
    ls = LightSampler(lights, scene.device)
    gen = torch.Generator().manual_seed(2)
    x = 30 * torch.randn(3000, 3, generator=gen)
    u = torch.rand(3000, 4, generator=gen)
    want = ls.sample(x, u)
    table = LightTable(ls)
    lanes = ([u[:, 0]] if ls.n_lights > 1 else []) + ([u[:, 1], u[:, 2]] if ls.has_uniform_env else [])
    values = [torch.tensor(v) for v in table.values]  # as the compiled step reads them from its input
    wi, dist, weight, light_pdf, is_env = table.sample(values, v3(x), lanes)
    np.testing.assert_allclose(torch.stack(wi, 1).numpy(), want.wi.numpy(), atol=1e-6)
    np.testing.assert_allclose(dist.numpy(), want.distance.numpy(), rtol=1e-6)
    np.testing.assert_allclose(torch.stack(weight, 1).numpy(), want.weight.numpy(), rtol=1e-5)
    np.testing.assert_allclose(light_pdf.numpy(), want.light_pdf.numpy(), rtol=1e-6)
    assert torch.equal(is_env, want.is_env)
    if ls.has_env:
        np.testing.assert_allclose(table.values[-1], ls.env_pdf(want.wi).numpy(), rtol=1e-6)


# ---------------------------------------------------------------------------------------------- RNG
def test_hash_rng_is_uniform_deterministic_and_decorrelated():
    keys = path_key(7, torch.arange(20000))
    assert len(torch.unique(keys)) == len(keys)  # the hash is a bijection of 32-bit values
    lanes = uniforms(keys, torch.full_like(keys, 3), 4)
    u = torch.stack(lanes + uniforms(keys, torch.full_like(keys, 4), 1), 1)
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    # chi-square over 32 bins per lane (31 dof: 99.99 % quantile ~ 70), means and cross-correlations
    for j in range(u.shape[1]):
        counts = torch.bincount((u[:, j] * 32).long(), minlength=32).double()
        chi2 = float(((counts - len(u) / 32) ** 2 / (len(u) / 32)).sum())
        assert chi2 < 70, (j, chi2)
    np.testing.assert_allclose(u.mean(0).numpy(), 0.5, atol=0.01)
    corr = np.corrcoef(u.T.numpy())
    assert np.abs(corr - np.eye(len(corr))).max() < 0.04
    # neighbouring sample ids and seeds give unrelated streams; same inputs, same numbers
    assert torch.equal(uniforms(keys, torch.full_like(keys, 3), 4)[2], lanes[2])
    other = uniforms(path_key(8, torch.arange(20000)), torch.full_like(keys, 3), 1)[0]
    assert abs(np.corrcoef(other.numpy(), lanes[0].numpy())[0, 1]) < 0.04
    assert int(hash32(torch.tensor([0, 1, 2**32 - 1])).max()) < 2**32


def test_hash_rng_draws_the_same_numbers_at_every_batch_size():
    """Eager draws of few numbers hash all lanes at once (``EAGER_LANES_MAX``), larger ones a lane at a time (the
    form compiled code keeps): a path's numbers are bitwise the same at every batch size. (Compiled against eager:
    the compiled backend's parity tests, long set.)"""
    from nrc.transport.rng import EAGER_LANES_MAX

    keys = path_key(3, torch.arange(EAGER_LANES_MAX))
    ctr = torch.arange(EAGER_LANES_MAX) % 7
    big = uniforms(keys, ctr, 6)  # 6 x 2^14 numbers: one lane at a time
    for n in (2, 100, EAGER_LANES_MAX // 6):  # all lanes at once
        for got, want in zip(uniforms(keys[:n], ctr[:n], 6), big):
            assert torch.equal(got, want[:n])
    assert torch.equal(uniforms(keys[:50], ctr[:50], 1)[0], big[0][:50])


# ---------------------------------------------------------------------------------------------- render level
SKY = ["scene=sky", "scene.camera.width=8", "scene.camera.height=6", "scene.camera.position=[0,0,120]",
       "scene.camera.look_at=[0,0,0]", "scene.camera.fov_y=50"]


@pytest.mark.parametrize("g", [0.0, 0.8])
def test_furnace_non_absorbing_medium_under_uniform_sky_is_invisible(g, single_thread):
    pt, _ = make(SKY + ["scene.volume.albedo=1", "scene.volume.density_scale=0.08", f"scene.volume.g={g}",
                        "scene.integrator.max_scatter=100", "scene.integrator.spp=128"])
    img = render_sm(pt).image
    L = np.array([0.35, 0.5, 0.8], dtype=np.float32)
    np.testing.assert_allclose(img.reshape(-1, 3).mean(0), L, rtol=0.02)
    assert np.all(np.abs(img - L) < 0.2 * L)


def test_deterministic_and_independent_of_the_working_set(single_thread):
    base = ["scene=sun_sky", "scene.camera.width=8", "scene.camera.height=4", "scene.integrator.spp=2",
            "scene.integrator.max_scatter=8"]
    a = render_sm(make(base)[0])
    b = render_sm(make(base)[0]).image
    c = render_sm(make(base + ["renderer.slots=37", "renderer.steps_per_call=3"])[0]).image
    d = render_sm(make(base + ["scene.integrator.seed=5"])[0]).image
    assert np.array_equal(a.image, b)
    # numbers depend on (seed, sample id, step) only: other slot counts add the same paths in another order
    np.testing.assert_allclose(c, b, rtol=1e-5, atol=1e-6)
    assert not np.array_equal(b, d)
    assert a.metrics["backend"] == "eager" and a.metrics["tracking_steps"] > 0


@pytest.mark.parametrize("spp", [1, 4])
def test_the_fused_tail_traces_the_same_paths(single_thread, monkeypatch, spp):
    """The driver's tail (fused calls: a tracking step and the vertices it reaches, Machine.advance) takes each path
    through the same steps with the same draws as the main loop (a tracking call, then a vertex pass): at 1 spp the
    image is bitwise equal with the tail off, from the first call on, or only at the end; at 4 spp a pixel's samples
    are harvested in another order (float rounding)."""
    import nrc.render.wavefront.driver as drv

    base = ["scene=sun_sky", "scene.camera.width=12", "scene.camera.height=6", f"scene.integrator.spp={spp}",
            "scene.integrator.max_scatter=24", "scene.volume.density_scale=3"]
    images, tails = {}, {}
    for slots, calls in ((0, 8), (1 << 20, 1), (16, 3)):
        monkeypatch.setattr(drv, "TAIL_SLOTS", slots)
        monkeypatch.setattr(drv, "TAIL_CALLS", calls)
        r = render_sm(make(base)[0])
        images[slots], tails[slots] = r.image, r.metrics.get("tail_calls", 0)
    assert tails[0] == 0 and tails[1 << 20] > 0 and tails[16] > 0
    for slots in (1 << 20, 16):
        if spp == 1:
            assert np.array_equal(images[slots], images[0])
        else:
            np.testing.assert_allclose(images[slots], images[0], rtol=1e-5, atol=1e-6)


HARD = [
    ["scene.volume.g=-0.999"],
    ["scene.volume.g=0.999"],
    ["scene.volume.density_scale=4", "scene.integrator.max_scatter=4"],  # ~700 steps per crossing
    # single-voxel bricks; 8 paths (its cost is work, not the chain: 48 paths took 115 s, 6 paths 13 s)
    pytest.param(["scene.volume.density_scale=10000", "scene.integrator.max_scatter=4", "scene.camera.width=4",
                  "scene.camera.height=2", "scene.integrator.spp=1"], marks=pytest.mark.slow),
    ["renderer.free_flight=global", "renderer.brick=2"],  # two tables: global free flights, brick shadow rays
    ["scene=point", "scene.camera.position=[0,-15,5]"],  # camera and point light inside the volume
    ["renderer.russian_roulette.enabled=true", "renderer.russian_roulette.start=1"],
]


@pytest.mark.parametrize("overrides", HARD)
def test_hard_cases_stay_finite(overrides, single_thread):
    pt, _ = make(["scene=sun_sky", "scene.camera.width=6", "scene.camera.height=4", "scene.integrator.spp=2",
                  "scene.integrator.max_scatter=8", *overrides])
    img = render_sm(pt).image
    assert np.isfinite(img).all() and (img >= 0).all()


def test_empty_grid_shows_the_sky(single_thread):
    pt, _ = make(["scene=sun_sky", "scene.camera.width=6", "scene.camera.height=4", "scene.integrator.spp=4"],
                 torch.zeros(9, 9, 9))
    img = render_sm(pt).image
    np.testing.assert_allclose(img, np.broadcast_to([0.35, 0.5, 0.8], img.shape), rtol=1e-6)


@pytest.mark.parametrize("majorants", [[], ["renderer.brick=1"], ["renderer.free_flight=global"]])
def test_matches_the_eager_tracer_on_an_absorbing_medium(majorants, single_thread):
    """Transmittance of camera rays only (albedo 0): per-pixel agreement within Monte Carlo error, with the
    default bricks, single-voxel bricks (many crossings per ray) and one global majorant."""
    pt, _ = make(SKY + ["scene.volume.albedo=0", "scene.volume.density_scale=0.05", "scene.integrator.spp=512",
                        *majorants])
    a, b = render_sm(pt).image, pt.render().image
    L = np.array([0.35, 0.5, 0.8], dtype=np.float32)
    se = L * np.sqrt(2 * 0.25 / 512)  # two estimates, Bernoulli variance <= 1/4
    assert np.all(np.abs(a - b) < 4.5 * se)


# ---------------------------------------------------------------------------------------------- backend choice
def test_backend_choice_and_fallback_reasons(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "empty-cache"))
    base = ["scene.camera.width=4", "scene.camera.height=2", "scene.integrator.spp=1", "scene.integrator.max_scatter=4"]
    with pytest.raises(ConfigError, match="renderer.backend"):
        make(base + ["renderer.backend=fast"])
    with pytest.raises(ConfigError, match="renderer.steps_per_call"):
        make(base + ["renderer.steps_per_call=0"])
    pt, _ = make(base + ["renderer.backend=auto", "renderer.compile_min_samples=1000"])
    r = pt.render()
    assert r.metrics["backend"] == "eager" and "compile_min_samples" in r.metrics["backend_reason"]
    # every estimator and dense media have a compiled form (other estimators: queued shadow rays)
    for extra in (["transmittance=track_length"], ["scene.volume.density_scale=10000"]):
        assert make(base + extra)[0].core.unsupported_reason() is None
    pt, _ = make(base + ["renderer.backend=eager"])
    assert pt.render().metrics["backend_reason"] is None


def test_auto_compiles_when_the_cache_holds_the_step(tmp_path, monkeypatch):
    """``auto`` weighs a compile against the work only when it would be cold: a marker of a finished compile of
    the same structure in the cache directory makes it choose ``compiled`` (torch.compile is lazy: the choice is
    read before anything compiles, through ``choose``'s inputs)."""
    from nrc.render.wavefront import machine as wm

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(wm, "AOT_DEVICES", ())  # torch.compile's marker, as on CUDA (the packages: the next test)
    pt, _ = make(["scene.camera.width=4", "scene.camera.height=2", "renderer.backend=auto",
                  "renderer.compile_min_samples=1000"])
    assert not wm.is_cached(pt.core.step, pt.device)
    wm._marker(pt.core.step, pt.device).touch()
    assert wm.is_cached(pt.core.step, pt.device)
    # a cached step is loaded only for renders that repay the ~4 s load (warm_fraction of compile_min_samples)
    machine, backend, reason = pt.core.choose(100)
    assert backend == "eager" and "loading the cached compiled step" in reason
    other, _ = make(["scene.camera.width=4", "scene.camera.height=2", "scene.volume.g=0.1",
                     "scene.volume.density_scale=3", "renderer.backend=auto"])
    assert wm.is_cached(other.core.step, other.device)  # scene numbers are not part of the structure
    no_sky, _ = make(["scene=sun_front", "scene.camera.width=4", "scene.camera.height=2"])  # another structure
    assert not wm.is_cached(no_sky.core.step, no_sky.device)
    # CPU kernels are specialised on the thread count: a joblib worker with fewer threads has no cached step
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(threads + 1)
        assert not wm.is_cached(pt.core.step, pt.device)
    finally:
        torch.set_num_threads(threads)
    assert wm.is_cached(pt.core.step, pt.device)


def test_latlong_environment_falls_back_with_a_reason(tmp_path):
    from nrc.io import write_exr

    write_exr(tmp_path / "env.exr", np.ones((4, 8, 3), dtype=np.float32))
    pt, _ = make(["scene=sky", "scene.lights.0.radiance=null", f"scene.lights.0.path={tmp_path / 'env.exr'}",
                  "renderer.backend=compiled", "scene.camera.width=4", "scene.camera.height=2",
                  "scene.integrator.spp=1"])
    r = pt.render()
    assert r.metrics["backend"] == "eager" and "environment maps" in r.metrics["backend_reason"]


# ---------------------------------------------------------------------------------------------- vs Mitsuba
CASES = {"sun_sky": [], "point": ["scene.lights.0.position=[30,70,40]"]}


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("preset", list(CASES))
def test_state_machine_matches_mitsuba(preset, single_thread):
    bridge = pytest.importorskip("nrc.evaluation.mitsuba_bridge")
    if not bridge.mitsuba_available():
        pytest.skip("Mitsuba 3 is not installed")
    from test_pt_vs_mitsuba import compare_with_mitsuba

    compare_with_mitsuba(CASES[preset], preset, render=render_sm, seeds=8)  # fast: more seeds, steadier SEs



def test_the_step_imports_only_what_its_aot_key_hashes():
    """The AOT packages are keyed by the sources of ``STEP_SOURCES``: the step's code may reach no other part of
    nrc (besides errors, file I/O and the compile cache's location, which the traced step never calls), or an edit
    there would leave a stale package in use."""
    import subprocess
    import sys

    from nrc.render.compile_cache import STEP_SOURCES

    code = "import sys, nrc.render.wavefront.step; print(' '.join(m for m in sys.modules if m.startswith('nrc.')))"
    mods = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    allowed = tuple("nrc." + d.removesuffix(".py").replace("/", ".") for d in STEP_SOURCES) + (
        "nrc.errors", "nrc.io", "nrc.render.compile_cache")
    stray = [m for m in mods if m != "nrc.render" and not any(m == a or m.startswith(a + ".") for a in allowed)]
    assert "nrc.render.wavefront.step" in mods and not stray, stray
    # the renderers' vertex programs (files of STEP_SOURCES) import only from STEP_SOURCES too
    for d in STEP_SOURCES:
        if d.endswith(".py"):
            for target in imports(REPO / "nrc" / d):
                if target.startswith("nrc"):
                    assert any(target == a or target.startswith(a + ".") for a in allowed), (d, target)


def test_every_vertex_program_is_in_the_aot_key():
    """The vertex programs and hooks the renderers give the step are defined in files the AOT key hashes."""
    import inspect

    from nrc.render.radiance_caching.vertex import NRCVertex
    from nrc.render.reuse import ReuseHook
    from nrc.render.compile_cache import STEP_SOURCES

    for cls in (NRCVertex, ReuseHook):
        rel = Path(inspect.getfile(cls)).resolve().relative_to(REPO / "nrc").as_posix()
        assert any(rel == d or rel.startswith(d + "/") for d in STEP_SOURCES), rel


def test_a_segment_that_skips_the_environment_is_a_named_state_field():
    """``Decision.skip_env`` lives in the state field ``skip_env``, present where the program or a hook declares
    ``skips_env`` (no sign carried in ``pdf``); a program that sets it undeclared gets one clear error."""
    from nrc.render.wavefront import build_core
    from nrc.render.wavefront.program import Decision, VertexProgram

    pt = make(["renderer.backend=eager"])[0]
    assert not pt.core.step.layout.skip_env  # pt without reuse: the field does not exist
    light_only = make(["renderer.backend=eager", "renderer.reuse.mode=spatial", "renderer.reuse.domain=distance"])[0]
    assert light_only.core.step.layout.skip_env

    class Undeclared(VertexProgram):
        def at_vertex(self, s, n_s, beta_s, albedo, prm, u):
            go = torch.ones_like(n_s, dtype=torch.bool)
            return Decision(go=go, nee=go, mis=go, nee_beta=beta_s, beta=beta_s, skip_env=n_s == 1)

    class Declared(Undeclared):
        own_skips_env = True

    for program in (Undeclared(), Declared()):
        core = build_core(pt.scene, pt.transmittance, pt.settings, program)
        ly = core.step.layout
        F, I = ly.zeros(4, "cpu")
        F[ly.f("d")] = torch.tensor([[0.0], [0.0], [1.0]]).expand(3, 4)
        I[ly.i("n")] = torch.tensor([0, 0, 1, 1])  # vertices 1, 1, 2, 2
        args = (core.inputs.P, core.inputs.density, core.inputs.majorant)
        if isinstance(program, Declared):
            F, I = core.step.vertex(F, I, *args)
            assert I[ly.i("skip_env")].tolist() == [1, 1, 0, 0] and bool((F[ly.f("pdf")] > 0).all())
        else:
            with pytest.raises(TypeError, match="Undeclared sets Decision.skip_env but does not declare skips_env"):
                core.step.vertex(F, I, *args)


def test_one_machine_serves_every_scene_of_a_structure():
    """Tracers of other scenes (another grid, g, albedo, density scale, light, camera, spp, seed) share one machine:
    their numbers are step inputs. Another light structure or estimator gets its own."""
    from nrc.render.wavefront.machine import machine_for

    def machine(overrides):
        pt = make(["renderer.backend=compiled", *overrides])[0]
        return machine_for(pt.core.step, 1, True, pt.device)

    m = machine([])
    assert machine(["scene.volume.g=0.3", "scene.volume.albedo=0.5", "scene.volume.density_scale=2",
                    "scene.camera.width=9", "scene.integrator.spp=3", "scene.integrator.seed=4",
                    "scene.lights.0.direction=[0,-1,0]", "scene.volume.procedural.resolution=20"]) is m
    assert machine(["scene=sun_front"]) is not m  # the sun without a sky: another light structure
    assert machine(["transmittance=residual_ratio"]) is not m


@pytest.mark.slow
@pytest.mark.first(0)  # a cold compile of minutes: start it before the rest
def test_compiled_step_renders_a_second_scene_without_recompiling(fresh_machines, monkeypatch, caplog):
    """A real compile (cold cache): the first scene compiles the step once; a second scene with another grid
    shape, density scale, g, albedo, light direction and camera recompiles nothing (Dynamo's graphs and the AOT
    packages built, ``compiled_graphs``), and the compiled images agree with the eager backend within Monte Carlo
    error."""
    from conftest import assert_images_agree
    from nrc.render.wavefront.machine import compiled_graphs

    before = compiled_graphs()
    base = ["scene.camera.width=8", "scene.camera.height=4", "scene.integrator.spp=64", "scene.integrator.max_scatter=8"]
    first = make(base + ["renderer.backend=compiled"])[0].render()
    assert first.metrics["backend"] == "compiled", first.metrics["backend_reason"]
    frames_first = compiled_graphs()
    assert frames_first >= before + 1
    second_cfg = base + ["scene.volume.procedural.resolution=20", "scene.volume.density_scale=2.5",
                         "scene.volume.g=0.3", "scene.volume.albedo=0.7", "scene.lights.0.direction=[0.3,-1,-0.2]",
                         "scene.camera.position=[10,0,120]"]
    images = {}
    for backend in ("compiled", "eager"):
        images[backend] = [make(second_cfg + [f"renderer.backend={backend}", f"scene.integrator.seed={s}"])[0]
                           .render() for s in range(4)]
    assert all(r.metrics["backend"] == "compiled" for r in images["compiled"])
    assert compiled_graphs() == frames_first  # nothing recompiled for the second scene
    assert_images_agree([r.image for r in images["compiled"]], [r.image for r in images["eager"]], block=4)
    # on the CPU the step is two AOT packages: a new process (no machines) loads them; a corrupt one is rebuilt
    from nrc.render.wavefront import machine as wm

    pt = make(second_cfg + ["renderer.backend=compiled"])[0]
    paths = wm.aot_packages(pt.core.step, pt.core.steps_per_call, pt.device)
    assert paths is not None and all(p.is_file() for p in paths)
    wm._machines.clear()
    again = make(second_cfg + ["renderer.backend=compiled", "scene.integrator.seed=0"])[0].render()
    assert again.metrics["compile_cache_hit"] and compiled_graphs() == frames_first
    np.testing.assert_array_equal(again.image, images["compiled"][0].image)  # same kernels, same seed
    good = paths[1].read_bytes()
    paths[1].write_bytes(b"not a package")
    # the rebuild is the build tested above: here it restores the good file instead of compiling again (minutes)
    monkeypatch.setattr(wm, "_build_package", lambda fn, args, options, path: path.write_bytes(good))
    wm._machines.clear()
    with caplog.at_level(logging.WARNING, logger="nrc"):
        rebuilt = make(second_cfg + ["renderer.backend=compiled", "scene.integrator.seed=0"])[0].render()
    assert any("cannot be loaded" in r.getMessage() for r in caplog.records)
    assert rebuilt.metrics["backend"] == "compiled" and compiled_graphs() == frames_first + 1
    np.testing.assert_array_equal(rebuilt.image, images["compiled"][0].image)


def test_auto_loads_cached_packages_for_any_render(tmp_path, monkeypatch):
    """With the step's AOT packages in the cache (a load of milliseconds) ``auto`` compiles even a tiny render;
    the packages are keyed by the thread count and the structure, not by the scene's numbers."""
    from nrc.render.wavefront import machine as wm

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(wm, "_machines", [])
    pt, _ = make(["scene.camera.width=4", "scene.camera.height=2", "renderer.backend=auto",
                  "renderer.compile_min_samples=1000"])
    paths = wm.aot_packages(pt.core.step, pt.core.steps_per_call, pt.device)
    assert paths is not None and not wm.packages_cached(pt.core.step, pt.core.steps_per_call, pt.device)
    wm._marker(pt.core.step, pt.device).touch()  # a torch.compile build's marker is not a package
    assert not wm.is_cached(pt.core.step, pt.device) and pt.core.choose(100)[1] == "eager"
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.touch()
    monkeypatch.setattr(wm.Machine, "warm_up", lambda self, inputs, slots: 0.0)  # no real load
    assert wm.is_cached(pt.core.step, pt.device) and pt.core.choose(100)[1] == "compiled"
    other, _ = make(["scene.camera.width=4", "scene.camera.height=2", "scene.volume.g=0.1", "renderer.backend=auto"])
    assert wm.aot_packages(other.core.step, other.core.steps_per_call, other.device) == paths
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(threads + 1)
        assert wm.aot_packages(pt.core.step, pt.core.steps_per_call, pt.device) != paths
    finally:
        torch.set_num_threads(threads)


WRAPPER = """\
namespace torch::aot_inductor {
void AOTInductorModel::run_impl(
) {
    AOTI_TORCH_ERROR_CODE_CHECK(aoti_torch_empty_strided(1, int_array_5, int_array_1, cached_torch_dtype_float32, cached_torch_device_type_cpu, this->device_idx_, &buf113_handle));
    AOTI_TORCH_ERROR_CODE_CHECK(aoti_torch_empty_strided(1, int_array_2, int_array_1, cached_torch_dtype_int64, cached_torch_device_type_cpu, this->device_idx_, &buf130_handle));
    auto buf60 = wrap_with_raii_handle_if_needed(reinterpret_tensor_wrapper(buf113, 1, int_array_3, int_array_4, 6L*s21));  // alias
    auto buf116 = wrap_with_raii_handle_if_needed(reinterpret_tensor_wrapper(buf130, 1, int_array_3, int_array_4, 2L*s21));  // alias
    auto buf61 = wrap_with_raii_handle_if_needed(reinterpret_tensor_wrapper(buf113, 1, int_array_3, int_array_4, 7L*s21));  // alias
    auto buf62 = wrap_with_raii_handle_if_needed(reinterpret_tensor_wrapper(buf113, 1, int_array_3, int_array_4, s21));  // alias
    auto buf70 = wrap_with_raii_handle_if_needed(reinterpret_tensor_wrapper(buf77, 1, int_array_3, int_array_4, s21));  // alias
    auto buf77 = std::move(buf17);  // reuse
    cpp_fused_0((float*)(buf60.data_ptr()), (int64_t*)(buf116.data_ptr()), (float*)(buf61.data_ptr()), (float*)(buf62.data_ptr()), (float*)(buf70.data_ptr()), s21);
    output_handles[0] = buf61.release();
    buf113.reset();
    cpp_fused_1((float*)(buf62.data_ptr()), s21);
} // AOTInductorModel::run_impl
}
"""


def test_row_views_become_pointers_only_where_that_is_the_same_thing():
    """The AOT wrapper's per-row tensor views become pointers into their base (offset x element size) when they
    are used only as ``data_ptr()``; a view used as a tensor, one of a base of unknown type, and one used after its
    base is freed stay as Inductor wrote them."""
    from nrc.render.wavefront.row_views import raw_row_views

    code, n = raw_row_views(WRAPPER)
    assert n == 2
    assert "NrcRowPointer buf60{static_cast<char*>(buf113.data_ptr()) + (6L*s21) * 4};" in code
    assert "NrcRowPointer buf116{static_cast<char*>(buf130.data_ptr()) + (2L*s21) * 8};" in code
    for kept in ("buf61", "buf62", "buf70"):  # released as an output; used after buf113.reset(); base a reuse
        assert f"auto {kept} = wrap_with_raii_handle_if_needed(" in code
    assert code.count("struct NrcRowPointer") == 1 and code.index("struct NrcRowPointer") < code.index("run_impl")
    assert raw_row_views(WRAPPER.replace("run_impl", "other")) == (WRAPPER.replace("run_impl", "other"), 0)


@pytest.mark.slow  # an ahead-of-time compile (~20-40 s, the wrapper's C++ build): the long set
def test_a_package_with_row_pointers_computes_what_eager_code_does(tmp_path):
    """A step-like function that returns a stack of rows, built ahead of time with the rows as pointers, gives the
    eager function's output (integers bitwise, floats within rounding: compiled arithmetic), at several row
    lengths (the slot count is dynamic)."""
    from torch._inductor import aoti_compile_and_package, aoti_load_package
    from torch.export import Dim

    from nrc.render.wavefront.row_views import plain_row_views

    class Rows(torch.nn.Module):
        def forward(self, F, I):
            a, b, c = F.unbind(0)
            k = I[0]
            return torch.stack([a * b + 1, torch.where(k > 2, c, -c), b.sqrt(), a + c]), torch.stack([k + 1, k * 3])

    n = Dim("slots", min=2)
    F, I = torch.rand(3, 8), torch.arange(8)[None].clone()
    program = torch.export.export(Rows(), (F, I), dynamic_shapes=({1: n}, {1: n}), strict=False)
    report: dict[str, int] = {}
    with plain_row_views(report):
        path = aoti_compile_and_package(program, package_path=str(tmp_path / "rows.pt2"))
    assert report["row_views"] > 0
    step = aoti_load_package(path)
    for slots in (2, 5, 37):
        F, I = torch.rand(3, slots), torch.randint(0, 5, (1, slots))
        for got, want in zip(step(F, I), Rows()(F, I)):
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
