"""Reservoir reuse (ReSTIR) at the render paths' first vertex: merge invariants, unbiasedness against a brute-force
sum over the lights, camera reprojection, and block tests of the path tracer and NRC with reuse."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch

from conftest import assert_images_agree, compose
from nrc.camera import Camera
from nrc.errors import ConfigError
from nrc.render.pt import PathTracerSettings
from nrc.render.registry import make_renderer
from nrc.render.reuse import (DistanceReuse, ExtinctionTable, ReservoirReuse, Reservoirs, ReuseSettings,
                              VertexRecord)
from nrc.render.reuse import extinction
from nrc.scene import load_scene
from nrc.transport.light_sampling import LightSampler
from nrc.transport.lights import luminance3
from nrc.transport.phase import hg_pdf

SMALL = ["scene.volume.procedural.resolution=24", "scene.camera.width=40", "scene.camera.height=24"]


def _ones(grid, majorants, o, w, t0, t1, gen):
    return torch.ones_like(t0)  # a transmittance of 1: the brute-force sum is exact


def _vertices(scene, seed: int = 1) -> VertexRecord:
    """One vertex per pixel along its camera ray inside the box (coherent, as a real frame's first vertices)."""
    cam = scene.camera
    n = cam.num_pixels
    g = torch.Generator().manual_seed(seed)
    o, d = cam.generate_rays(torch.arange(n), torch.rand(n, 2, generator=g))
    t0, t1 = scene.grid.box.intersect(o, d)
    rec = VertexRecord.empty(n, 1, 1.0, torch.device("cpu"))
    rec.x[:] = o + d * (t0 + (t1 - t0) * torch.rand(n, generator=g))[:, None]
    rec.d[:], rec.beta[:] = d, 1.0
    rec.valid[:] = t1 > t0
    return rec


def _exact(lights: LightSampler, rec: VertexRecord, g: float) -> torch.Tensor:
    """The unshadowed direct light at each vertex without MIS: the sum over the delta lights, plus the uniform
    sky's radiance (the phase function integrates to one)."""
    n = rec.n
    out = lights.uniform_env.expand(n, 3).clone()
    for k in range(len(lights.directional) + len(lights.points)):
        wi, _, c, _ = lights.evaluate(torch.full((n,), k), torch.zeros(n, 3), rec.x)
        out += c * hg_pdf(g, (rec.d * wi).sum(-1))[:, None]
    return torch.where(rec.valid[:, None], out, torch.zeros_like(out))


def test_merge_keeps_the_confidence_sum_and_the_contribution_weight():
    """Combining a reservoir with invalid inputs leaves it as it was; with valid ones the confidence is the sum,
    the sample is one of the inputs' and ``W = sum w / p_hat(y)``."""
    cfg = compose(["scene=many_lights", *SMALL])
    scene = load_scene(cfg.scene)
    lights = LightSampler.for_scene(scene, "ris", 4)
    rec = _vertices(scene)
    rr = ReservoirReuse(ReuseSettings("spatial", target="unshadowed"), scene.g, 1, scene.grid)
    gen = torch.Generator().manual_seed(3)
    a = rr.initial(rec, lights, gen)
    b = rr.initial(rec, lights, gen)
    v = rec.valid
    assert torch.equal(a.M[v], torch.full_like(a.M[v], 4.0)) and bool((a.M[~v] == 0).all())
    dead = Reservoirs(b.light, b.omega, b.W, b.M, b.x, b.d, b.mis, torch.zeros_like(b.valid))
    same, sel = rr.combine([a, dead], lights, torch.rand(rec.n, generator=gen))
    assert bool((sel == 0).all())
    torch.testing.assert_close(same.W, a.W, rtol=1e-5, atol=0)
    assert torch.equal(same.light, a.light) and torch.equal(same.M, a.M)
    # b at shifted vertices: a second domain
    b.x = b.x + 0.5
    both, sel = rr.combine([a, b], lights, torch.rand(rec.n, generator=gen))
    torch.testing.assert_close(both.M[v], a.M[v] + b.M[v])
    picked = torch.where(sel == 0, a.light, b.light)
    assert torch.equal(both.light, picked)
    ph = [rr.target(lights, r.light, r.omega, r.x, r.d, r.mis) for r in (a, b)]  # own targets
    cross = [rr.target(lights, r.light, r.omega, o.x, o.d, o.mis) for r, o in ((a, b), (b, a))]
    p0 = [ph[0], rr.target(lights, b.light, b.omega, a.x, a.d, a.mis)]  # at the receiver (a's vertices)
    w = [a.M * ph[0] / (a.M * ph[0] + b.M * cross[0]) * p0[0] * a.W,
         b.M * ph[1] / (b.M * ph[1] + a.M * cross[1]) * p0[1] * b.W]
    total = (w[0] + w[1])[v]
    expect = total / torch.where(sel == 0, p0[0], p0[1])[v]
    ok = total > 0
    torch.testing.assert_close(both.W[v][ok], expect[ok], rtol=1e-4, atol=0)


@pytest.mark.parametrize("mis", ["balance", "pairwise"])
def test_mis_weights_sum_to_one_for_a_shared_sample(mis):
    """Five inputs at different vertices holding the same light sample: their MIS weights (each input's own,
    at its own sample) sum to one wherever the receiver's target is positive, an input with no confidence
    gets none, and the receiver keeps all of it when no neighbour is valid."""
    cfg = compose(["scene=many_lights", *SMALL])
    scene = load_scene(cfg.scene)
    lights = LightSampler.for_scene(scene, "ris", 4)
    rr = ReservoirReuse(ReuseSettings("spatial", target="unshadowed", mis=mis), scene.g, 1, scene.grid)
    gen = torch.Generator().manual_seed(5)
    base = rr.initial(_vertices(scene), lights, gen)
    inputs = []
    for k in range(5):
        rec = _vertices(scene, seed=10 + k)
        r = Reservoirs(base.light, base.omega, base.W, torch.full_like(base.M, float(1 + 3 * k)), rec.x, rec.d,
                       rec.mis, rec.valid & base.valid)
        inputs.append(r)
    inputs[3].M = torch.zeros_like(inputs[3].M)
    Ms = [torch.where(r.valid & inputs[0].valid, r.M, torch.zeros_like(r.M)) for r in inputs]
    p0 = [rr.target(lights, r.light, r.omega, inputs[0].x, inputs[0].d, inputs[0].mis) for r in inputs]
    m = rr._mis_weights(inputs, Ms, p0, lights)
    ok = inputs[0].valid & (p0[0] > 0)
    assert int(ok.sum()) > 100
    torch.testing.assert_close(sum(m)[ok], torch.ones(int(ok.sum())), rtol=1e-5, atol=1e-6)
    assert bool((m[3] == 0).all())
    for r in inputs[1:]:
        r.valid = torch.zeros_like(r.valid)
    Ms = [torch.where(r.valid & inputs[0].valid, r.M, torch.zeros_like(r.M)) for r in inputs]
    m = rr._mis_weights(inputs, Ms, p0, lights)
    torch.testing.assert_close(m[0][ok], torch.ones(int(ok.sum())))


def _assert_matches(mean: torch.Tensor, last: list, own: list, exact: torch.Tensor, v: torch.Tensor, camera,
                    lit_floor: float | None = None) -> None:
    """Per-pixel means over seeds ``(seeds, N)`` against ``exact`` ``(N,)``: image-wide over pixels ``v`` within
    4 standard errors, in 8x8 blocks (those above ``lit_floor`` x the brightest, all without) within 4.5; the
    last frames' error (``last``) below that of the own RIS (``own``)."""
    seeds = mean.shape[0]
    ratios = mean[:, v].mean(1) / exact[v].mean()
    z = (float(ratios.mean()) - 1.0) / (float(ratios.std()) / math.sqrt(seeds))
    assert abs(z) < 4.0, (z, ratios)
    H, W, B = camera.height, camera.width, 8
    blocks = mean.reshape(seeds, H // B, B, W // B, B).mean((2, 4))
    eb = exact.reshape(H // B, B, W // B, B).mean((1, 3))
    zb = (blocks.mean(0) - eb) / (blocks.std(0) / math.sqrt(seeds))
    lit = torch.ones_like(eb, dtype=torch.bool) if lit_floor is None else eb > lit_floor * eb.max()
    assert int(lit.sum()) >= 10 and float(zb[lit].abs().max()) < 4.5, zb
    err = lambda imgs: float(((torch.stack(imgs) - exact) ** 2)[:, v].mean() / (exact[v] ** 2).mean())  # noqa: E731
    assert err(last) < err(own)


@pytest.mark.parametrize("mode, mis", [("spatial", "balance"), ("spatial", "pairwise"), ("spatiotemporal", "pairwise")])
def test_reuse_is_unbiased_against_the_sum_over_the_lights(mode, mis):
    """16 point lights and a sky seen from one vertex per pixel of a 40x24 frame (fixed vertices, 6 frames of
    reuse, 24 seeds): the per-pixel mean over seeds matches the brute-force sum over the lights, image-wide
    within 4 standard errors and in 3x3 blocks of 8x8 pixels within 4.5 (a 3 % smaller contribution weight fails
    the image test by ~5 standard errors). The last frame's error is below that of the vertices' own RIS."""
    cfg = compose(["scene=many_lights", *SMALL])
    scene = load_scene(cfg.scene)
    lights = LightSampler.for_scene(scene, "ris", 4)
    rec = _vertices(scene)
    lum = lambda c: luminance3(c.unbind(-1))  # noqa: E731
    exact = lum(_exact(lights, rec, scene.g))
    seeds, frames = 24, 6
    mean, last, own = [], [], []
    for s in range(seeds):
        rr = ReservoirReuse(ReuseSettings(mode, target="unshadowed", mis=mis), scene.g, 1, scene.grid)
        gen = torch.Generator().manual_seed(100 + s)
        acc = torch.zeros(rec.n)
        for _ in range(frames):
            out, stats = rr.frame(rec, scene.camera, lights, _ones, scene.grid, None, gen, 1 << 20)
            acc += lum(out) / frames
        mean.append(acc)
        last.append(lum(out))
        own.append(lum(rr.shade(rr.initial(rec, lights, gen), rec, lights, _ones, scene.grid, None, gen, 1 << 20)))
    _assert_matches(torch.stack(mean), last, own, exact, rec.valid, scene.camera)
    assert stats["reuse_spatial_accept"] > 0.2 and stats["reuse_mean_m"] > 4
    if mode == "spatiotemporal":
        assert stats["reuse_temporal_found"] > 0.9  # a static camera finds the pixel's own history


def _single_scattering(scene, lights: LightSampler, jitters: int = 6, steps: int = 96) -> torch.Tensor:
    """Each pixel's unshadowed single scattering of the lights (no transmittance), by quadrature: the midpoint
    rule in ``steps`` steps along camera rays at ``jitters x jitters`` sub-pixel positions."""
    cam, grid = scene.camera, scene.grid
    n = cam.num_pixels
    out = torch.zeros(n)
    for a in range(jitters):
        for b in range(jitters):
            jit = torch.tensor([[(a + 0.5) / jitters, (b + 0.5) / jitters]]).expand(n, 2)
            o, d = cam.generate_rays(torch.arange(n), jit)
            ta, tb = grid.box.intersect(o, d)
            ta = ta.clamp(min=0.0)
            h = ((tb - ta) / steps).clamp(min=0.0)
            for k in range(steps):
                rec = VertexRecord.empty(n, 1, 1.0, torch.device("cpu"))
                rec.x[:] = o + d * (ta + (k + 0.5) * h)[:, None]
                rec.d[:], rec.valid[:] = d, tb > ta
                light = luminance3(_exact(lights, rec, scene.g).unbind(-1))
                out += scene.albedo * grid.sigma_t(rec.x) * light * h / jitters ** 2
    return out


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["spatial", "spatiotemporal"])
def test_distance_reuse_is_unbiased_against_quadrature(mode, monkeypatch):
    """``domain=distance`` (pairs of a camera-ray distance and a light sample) on 16 point lights and a sky,
    transmittance 1: the per-pixel mean over 24 seeds x 6 frames matches the quadrature of the camera rays'
    single scattering, image-wide within 4 standard errors and in 3x3 blocks of 8x8 pixels within 4.5; reuse
    lowers the error of the last frame below that of the rays' own RIS. A thin medium (optical depth <~ 1):
    the target's coarse transmittance then stays near the stub's 1 (a target far from the integrand is
    unbiased too, but its heavy tail would need far more seeds)."""
    # the shading's two transmittance estimates are 1 here (their own unbiasedness is tested below)
    monkeypatch.setattr(extinction._Table, "transmittance", lambda self, grid, t, points, gen: torch.ones_like(t))
    cfg = compose(["scene=many_lights", *SMALL, "scene.volume.density_scale=0.02"])
    scene = load_scene(cfg.scene)
    lights = LightSampler.for_scene(scene, "ris", 4)
    exact = _single_scattering(scene, lights)
    lum = lambda c: luminance3(c.unbind(-1))  # noqa: E731
    seeds, frames = 24, 6
    mean, last, own = [], [], []
    for s in range(seeds):
        rr = DistanceReuse(ReuseSettings(mode, domain="distance"), scene.g, 1, scene.grid, scene.albedo)
        gen = torch.Generator().manual_seed(300 + s)
        acc = torch.zeros(scene.camera.num_pixels)
        for _ in range(frames):
            out, stats = rr.frame(None, scene.camera, lights, _ones, scene.grid, None, gen, 1 << 20)
            acc += lum(out) / frames
        mean.append(acc)
        last.append(lum(out))
        first = rr.initial(scene.camera, scene.camera.num_pixels, lights, gen)
        own.append(lum(rr.shade(first, None, lights, _ones, scene.grid, None, gen, 1 << 20)))
    # a block that sees the cloud only at a few pixels' edges is a rare event: blocks below 1e-3 of the brightest
    # are left out
    _assert_matches(torch.stack(mean), last, own, exact, exact > 0, scene.camera, lit_floor=1e-3)
    assert stats["reuse_spatial_accept"] > 0.05 and stats["reuse_mean_m"] > 8
    if mode == "spatiotemporal":
        assert stats["reuse_temporal_found"] > 0.9


@pytest.mark.parametrize("steps", [16, 64])
def test_table_transmittance_is_unbiased_and_far_less_noisy_than_ratio_tracking(steps):
    """The distance domain's transmittance (residual ratio tracking against a ray's extinction table,
    ``_Table.transmittance``) on camera rays through a dense procedural cloud: the mean of 400 estimates per
    ray matches ``exp(-tau)`` by a 4096-step quadrature within 4.5 standard errors on every ray and on average,
    whether the table resolves the grid (64 steps) or not (16 steps: unbiased for any table); with 64 steps its
    variance is below a fifth of ratio tracking's on the same segments."""
    from nrc.render.registry import make_renderer

    cfg = compose(["renderer=pt", "scene=many_lights", *SMALL])
    scene = load_scene(cfg.scene)
    grid, cam = scene.grid, scene.camera
    o, d = cam.generate_rays(torch.arange(cam.num_pixels), torch.full((cam.num_pixels, 2), 0.5))
    ta, tb = grid.box.intersect(o, d)
    ta = ta.clamp(min=0.0)
    keep = (tb > ta).nonzero().squeeze(1)
    o, d, ta, tb = o[keep], d[keep], ta[keep], tb[keep]
    t = ta + 0.7 * (tb - ta)
    q = 4096
    h = (t - ta) / q
    tau = sum(grid.sigma_t(o + d * (ta + (k + 0.5) * h)[:, None]) * h for k in range(q))
    exact = torch.exp(-tau)
    assert float(tau.max()) > 2.0  # dense enough that the estimators differ
    reps = 400
    tab = ExtinctionTable.march(grid.sigma_t, o, d, ta, tb, steps).take(torch.arange(len(o)).repeat(reps))
    gen = torch.Generator().manual_seed(5)
    est = tab.transmittance(grid, t.repeat(reps), 8, gen).view(reps, -1)
    z = (est.mean(0) - exact) / (est.std(0) / math.sqrt(reps)).clamp(min=1e-7)
    assert float(z.abs().max()) < 4.5 and abs(float(z.mean())) < 4.5 / math.sqrt(len(z)) * 2
    if steps == 64:
        pt = make_renderer("pt", scene, cfg)
        ratio = pt.transmittance(grid, pt.majorants, o.repeat(reps, 1), d.repeat(reps, 1), ta.repeat(reps),
                                 t.repeat(reps), gen).view(reps, -1)
        assert float(est.var(0).sum()) < 0.2 * float(ratio.var(0).sum())


def test_distance_source_pdf_integrates_to_one_and_samples_follow_it():
    """The distance source on camera rays: its pdf integrates to one over ``[ta, tb]`` on every ray that crosses
    the box, and the samples' histogram along one ray follows it."""
    cfg = compose(["scene=many_lights", *SMALL])
    scene = load_scene(cfg.scene)
    rr = DistanceReuse(ReuseSettings("spatial", domain="distance"), scene.g, 1, scene.grid, scene.albedo)
    r = rr.rays(scene.camera, scene.camera.num_pixels, torch.Generator().manual_seed(0))
    assert int(r.valid.sum()) > 100
    steps = 4096
    integral = torch.zeros(len(r.ta))
    h = (r.tb - r.ta) / steps
    for k in range(steps):
        integral += rr.distance_pdf(r, r.ta + (k + 0.5) * h) * h
    np.testing.assert_allclose(integral[r.valid].numpy(), 1.0, atol=5e-3)
    i = int(torch.argmax(r.total() * r.valid))  # the densest ray: the exponential part matters most
    one = r.take(torch.full((200000,), i))
    g = torch.Generator().manual_seed(1)
    t = rr.sample_distance(one, torch.rand(200000, generator=g), torch.rand(200000, generator=g))
    edges = torch.linspace(float(one.ta[0]), float(one.tb[0]), 21)
    hist = torch.histogram(t, edges).hist / 200000
    sub = 400  # each bin's probability by the midpoint rule on 400 sub-steps (the pdf is steep in a bin)
    w = (edges[1] - edges[0]) / sub
    ts = edges[:-1, None] + (torch.arange(sub)[None, :] + 0.5) * w
    expect = rr.distance_pdf(one.take(torch.zeros(20 * sub, dtype=torch.long)), ts.reshape(-1)).reshape(20, sub)
    np.testing.assert_allclose(hist.numpy(), (expect.sum(1) * w).numpy(), atol=4e-3)


def test_reprojection_of_a_static_camera_is_the_identity_and_follows_a_moving_one():
    cfg = compose(["scene=sun", *SMALL])
    scene = load_scene(cfg.scene)
    cam: Camera = scene.camera
    n = cam.num_pixels
    g = torch.Generator().manual_seed(0)
    pix = torch.arange(n)
    o, d = cam.generate_rays(pix, 0.01 + 0.98 * torch.rand(n, 2, generator=g))
    x = o + d * (50.0 + 100.0 * torch.rand(n, 1, generator=g))
    got, inside = cam.project(x)
    assert bool(inside.all()) and torch.equal(got, pix)
    _, inside = cam.project(cam.position - 10.0 * cam.forward)  # behind the camera
    assert not bool(inside.any())
    # a camera moved to the right sees the same point further left
    moved = Camera.look_at(cam.position + 5.0 * cam.right, cam.position + 5.0 * cam.right + 100 * cam.forward,
                           cam.up, cam.fov_y, cam.width, cam.height)
    centre = torch.tensor([n // 2 + cam.width // 2])
    o, d = cam.generate_rays(centre, torch.full((1, 2), 0.5))
    p2, ok = moved.project(o + 200.0 * d)
    assert bool(ok.all()) and int(p2 % cam.width) < int(centre % cam.width)


@pytest.mark.parametrize("override, message", [
    ("renderer.reuse.mode=always", "renderer.reuse.mode must be one of"),
    ("renderer.reuse.radius=0.5", "renderer.reuse.radius must be >= 1.0"),
    ("renderer.reuse.neighbors=-1", "renderer.reuse.neighbors must be >= 0"),
    ("renderer.reuse.history=0", "renderer.reuse.history must be > 0.0"),
    ("+renderer.reuse.depth=2", "renderer.reuse: unknown key(s) depth"),
    ("renderer.reuse.mis=power", "renderer.reuse.mis must be one of"),
    ("renderer.reuse.domain=path", "renderer.reuse.domain must be one of"),
    ("renderer.reuse.distance_candidates=0", "renderer.reuse.distance_candidates must be >= 1"),
    ("renderer.reuse.distance_steps=0", "renderer.reuse.distance_steps must be >= 1"),
    ("renderer.reuse.target=exact", "renderer.reuse.target must be one of"),
])
def test_bad_reuse_settings_name_the_key(override, message):
    with pytest.raises(ConfigError) as err:
        PathTracerSettings.from_config(compose(["renderer=pt", override]).renderer)
    assert message in str(err.value)


def test_distance_reuse_under_nrc_needs_the_indirect_cache_target():
    from nrc.render.radiance_caching.settings import NRCSettings

    with pytest.raises(ConfigError, match="renderer.reuse.domain=distance needs renderer.cache_target=indirect"):
        NRCSettings.from_config(compose([*NRC_TINY, "renderer.reuse.domain=distance",
                                         "renderer.cache_target=full"]).renderer)


def test_deferred_reuse_starts_at_the_second_vertex_for_a_peaked_phase_function():
    st = ReuseSettings("spatial", defer_g=0.9)
    assert (st.vertex(0.5), st.vertex(0.95), st.vertex(-0.93), ReuseSettings().vertex(0.99)) == (1, 2, 2, 0)
    assert ReuseSettings("spatial", defer_g=0.9, domain="distance").vertex(0.95) == 1  # the camera ray's vertex


TINY = ["renderer=pt", "scene.volume.procedural.resolution=24", "scene.camera.width=16", "scene.camera.height=8",
        "scene.integrator.max_scatter=4", "renderer.backend=eager", "renderer.light_selection=ris"]


def _renders(extra: list[str], seeds: int = 4, first: int = 0) -> list[np.ndarray]:
    out = []
    for seed in range(first, first + seeds):
        cfg = compose([*TINY, *extra, f"scene.integrator.seed={seed}"])
        out.append(make_renderer("pt", load_scene(cfg.scene), cfg).render().image)
    return out


_PLAIN: dict[str, list[np.ndarray]] = {}  # scene -> the plain path tracer's renders (shared by the tests below)
SUN_SKY = pytest.mark.xdist_group("reuse_sun_sky")  # one worker renders the sun_sky plain images once (CI: loadgroup)


@pytest.mark.slow
@pytest.mark.parametrize("scene, mode, target, domain", [
    pytest.param("sun_sky", "spatiotemporal", "coarse", "light", marks=SUN_SKY),
    ("many_lights", "spatiotemporal", "unshadowed", "light"),
    pytest.param("sun_sky", "spatiotemporal", "unshadowed", "distance", marks=SUN_SKY)])
def test_path_tracer_with_reuse_agrees_with_the_path_tracer(scene, mode, target, domain):
    """The path tracer with reuse (32 one-sample passes, the MIS against the sky in the target and the shading)
    against the path tracer without (256 spp, other seeds), block-wise over 8 seeds each (with 4 seeds the
    3-degree-of-freedom t statistics of these heavy-tailed images reach |z| ~ 7 without any bias). With
    ``domain=distance`` the sky reached from the first vertex by phase sampling must not be counted again."""
    reuse = _renders([f"scene={scene}", f"renderer.reuse.mode={mode}", f"renderer.reuse.target={target}",
                      f"renderer.reuse.domain={domain}", "scene.integrator.spp=32"], seeds=8)
    if scene not in _PLAIN:  # independent paths (other seeds); the same for every reuse setting of a scene
        _PLAIN[scene] = _renders([f"scene={scene}", "scene.integrator.spp=256"], seeds=8, first=100)
    assert_images_agree(reuse, _PLAIN[scene])


@pytest.mark.slow
def test_compiled_step_structure_with_distance_reuse_agrees_with_the_eager_step():
    """The compiled backend's step structure (run eagerly: the code the compiled backend compiles) with
    ``domain=distance``, whose first vertex does no next-event estimate and does not count the sky its phase
    direction reaches (``ReuseHook.light_only``), against the eager step with the same reuse, block-wise over 8
    seeds each; and the structure's key names the light-only variant (one compiled graph per variant)."""

    def renders(structure: bool, first: int) -> list[np.ndarray]:
        out = []
        for seed in range(first, first + 8):
            cfg = compose([*TINY, "scene=sun_sky", "renderer.reuse.mode=spatial", "renderer.reuse.neighbors=0",
                           "renderer.reuse.domain=distance", "scene.integrator.spp=16",
                           f"scene.integrator.seed={seed}"])
            pt = make_renderer("pt", load_scene(cfg.scene), cfg)
            if structure:
                assert pt.core.step is not pt.core.eager_step  # shadow rays inside the step: other code
                assert ("reuse", 1, "light_only") in pt.core.step.program.structure
                pt.core.eager_step = pt.core.step
            out.append(pt.render().image)
        return out

    assert_images_agree(renders(True, 0), renders(False, 100))


NRC_TINY = ["renderer=nrc", "scene=sun_sky", "scene.volume.procedural.resolution=24", "scene.camera.width=16",
            "scene.camera.height=8", "renderer.training.width=8", "renderer.training.height=8",
            "cache.network.n_neurons=16", "cache.network.n_hidden_layers=1", "encoding.position.n_levels=4",
            "encoding.position.log2_hashmap_size=12", "renderer.reuse.mode=spatiotemporal",
            "renderer.animate.mode=orbit", "renderer.log.image_every=2"]


@pytest.mark.parametrize("domain", ["light", "distance"])
def test_nrc_with_reuse_logs_its_counters_and_resumes_exactly(tmp_path, domain):
    """NRC with spatiotemporal reuse on an orbiting camera: the counters reach metrics and TensorBoard, and a run
    resumed from the frame-3 checkpoint (which holds the reservoirs) ends with the same image."""
    cfg = compose([*NRC_TINY, "frames=6", "renderer.checkpoint_every=3", f"renderer.reuse.domain={domain}"])
    scene = load_scene(cfg.scene)
    full = make_renderer("nrc", scene, cfg)
    full.attach_output(tmp_path)

    def keep(frame, image, output, stats):
        if frame == 3:
            shutil.copy(tmp_path / "checkpoint.pt", tmp_path / "at3.pt")

    result = full.render(on_frame=keep)
    h = result.metrics["history"]
    assert result.metrics["reuse"] == "spatiotemporal" and result.metrics["reuse_vertex"] == 1
    assert result.metrics["reuse_domain"] == domain
    assert min(h["reuse_vertices"]) > 0 and h["reuse_temporal_found"][-1] > 0.5
    assert h["reuse_mean_m"][-1] > 4 * h["reuse_mean_m"][0]  # the history's confidence builds up
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ev = EventAccumulator(str(next((tmp_path / "tensorboard").iterdir()).parent))
    ev.Reload()
    assert "reuse/mean_m" in ev.Tags()["scalars"] and "reuse/temporal_accept" in ev.Tags()["scalars"]
    resumed = make_renderer("nrc", scene, compose([*NRC_TINY, "frames=6", "renderer.log.tensorboard=false",
                                          f"renderer.reuse.domain={domain}", f"renderer.resume={tmp_path / 'at3.pt'}"]))
    rest = resumed.render()
    np.testing.assert_allclose(rest.image, result.image, rtol=1e-5, atol=1e-6)


def test_reuse_with_no_light_left_to_sample_adds_nothing_and_runs():
    """Every light equi-angular (one point light): the reuse pass has no light to sample; the image is the
    equi-angular one, finite and lit."""
    cfg = compose([*TINY, "scene=point", "scene.volume.density_scale=0.05", "renderer.point_light_sampling=equiangular",
                   "renderer.reuse.mode=spatial",
                   "scene.integrator.spp=2"])
    res = make_renderer("pt", load_scene(cfg.scene), cfg).render()
    assert np.isfinite(res.image).all() and res.image.mean() > 0
    assert res.metrics["nee_lights"] == 0 and res.metrics["reuse_vertices"] > 0


@pytest.mark.slow
def test_bench_reuse_decomposition_runs_on_a_tiny_scene(tmp_path):
    """``scripts/bench_reuse.py --decompose`` on a tiny scene: the direct light's share is a fraction, every
    variant's figures are finite and positive, each variant's direct light has about the own RIS's mean, and
    the markdown has a row per variant."""
    import importlib.util
    import types

    from conftest import REPO

    spec = importlib.util.spec_from_file_location("bench_reuse", REPO / "scripts" / "bench_reuse.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    args = types.SimpleNamespace(frames=10, warmup=2, extra=[], out=tmp_path)
    tiny = "sun_sky:scene.camera.width=24,scene.camera.height=14,scene.volume.procedural.resolution=20"
    out = bench.decompose_scene(tiny, args, lambda msg: None)
    assert 0.0 < out["direct_share"] < 1.0 and out["passes_scored"] == 8
    assert len(out["variants"]) == 4
    for v in out["variants"].values():
        assert all(math.isfinite(x) and x > 0 for k, x in v.items() if k != "mean_direct_over_own")
        assert 0.5 < v["mean_direct_over_own"] < 1.5
    md = bench.decompose_markdown([out], {"machine": "-", "torch": "-", "code": "-", "frames": 10, "warmup": 2,
                                          "extra": []})
    assert md.count("spatiotemporal/") == 2 and "none (own RIS)" in md


@pytest.mark.slow
def test_bench_reuse_oracle_runs_on_a_tiny_scene(tmp_path):
    """``scripts/bench_reuse.py --oracle-nrc`` on a tiny scene: four estimators scored (none, own, reuse,
    oracle), finite figures, the single-scatter share a fraction, the oracle no slower than the reuse run, and a
    markdown row per estimator."""
    import importlib.util
    import types

    from conftest import REPO

    spec = importlib.util.spec_from_file_location("bench_reuse", REPO / "scripts" / "bench_reuse.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    args = types.SimpleNamespace(nrc_frames=5, nrc_warmup=1, ref_spp=8, extra=[], out=tmp_path)
    tiny = ("sun_sky:scene.camera.width=16,scene.camera.height=8,scene.volume.procedural.resolution=20,"
            "renderer.training.width=8,renderer.training.height=8,cache.network.n_neurons=16,"
            "cache.network.n_hidden_layers=1,encoding.position.n_levels=4,encoding.position.log2_hashmap_size=12,"
            "renderer.reuse.distance_steps=16")
    out = bench.oracle_nrc(tiny, args, lambda msg: None)
    assert set(out["estimators"]) == {"none", "own", "reuse", "oracle"} and out["frames_scored"] == 4
    assert 0.0 < out["single_scatter_share"] < 1.0
    for row in out["estimators"].values():
        assert all(math.isfinite(x) for x in row.values())
    est = out["estimators"]
    assert 0 < est["oracle"]["seconds_per_frame"] <= est["reuse"]["seconds_per_frame"]
    md = bench.oracle_markdown([out], {"machine": "-", "torch": "-", "code": "-", "nrc_frames": 5, "nrc_warmup": 1,
                                       "ref_spp": 8, "extra": []})
    assert all(f"| {k} |" in md for k in ("none", "own", "reuse", "oracle"))
