"""Unbiased NRC (``renderer.debias``): the cache as a control variate.

A render path that would terminate into the cache goes on with probability q as a path-traced suffix weighted
1/q, and the cache enters with weight 1 - 1/q. The tests: with a zero cache, q = 1 is the path tracer; with
q = 1 the cache drops out (bit for bit); with an oracle cache every q gives the path tracer's mean and q = 0 the
oracle image; with a wrong cache (the oracle x 0.5) q > 0 stays unbiased and q = 0 is measurably biased; under
``cache_target=indirect`` (where the continued vertex keeps its light-sampled direct light and the sky its first
direction reaches is not counted) the same on sun + sky; the diagnostics and the suffix training records.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import assert_images_agree, compose
from test_nrc import FULL, ORACLE, SEEDS, SMALL, ZERO, StubCache, render_images, sun_oracle
from nrc.errors import ConfigError
from nrc.render.registry import make_renderer
from nrc.scene import load_scene

# the oracle scene's paths stop at their last allowed vertex (2), where sun_oracle is exact
AT_ORACLE = [*ORACLE, *FULL, "renderer.termination.min_vertices=2"]


def zero(scene):
    return lambda x, d: torch.zeros_like(x)


def scaled(factor):
    def make(scene):
        fn = sun_oracle(scene)
        return lambda x, d: factor * fn(x, d)
    return make


def constant(value):
    return lambda scene: lambda x, d: torch.full_like(x, value)


def debias(q: float) -> list[str]:
    return [f"renderer.debias.probability={q}"]


@pytest.fixture(scope="module")
def pt_oracle():
    return render_images(ORACLE, SEEDS, "pt")


@pytest.mark.slow
@pytest.mark.parametrize("target", ["full", "indirect"])
def test_q1_with_a_zero_cache_is_the_path_tracer(target):
    """q = 1: every render path goes on past its cache termination (at vertex 1) to ``max_scatter``, so the image
    is the path tracer's, under sun and sky (under ``indirect``, the vertex's light-sampled estimate and the
    suffix without the sky its first direction reaches add up to the path tracer's MIS pair)."""
    scene = [*ZERO, "scene.integrator.max_scatter=4"]
    pt = render_images(scene, SEEDS, "pt")
    nrc = render_images([*scene, f"renderer.cache_target={target}", *debias(1.0)], SEEDS, "nrc", zero)
    assert_images_agree(nrc, pt)


def test_q1_cancels_any_cache():
    """With q = 1 the cache's weight is 1 - 1/q = 0: two very different caches give the same image, bit for bit."""
    a = render_images([*ZERO, *debias(1.0)], 2, "nrc", zero)
    b = render_images([*ZERO, *debias(1.0)], 2, "nrc", constant(5.0))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("q", [pytest.param(0.25, marks=pytest.mark.slow), 1.0])
def test_oracle_cache_every_q_gives_the_path_tracers_mean(q, pt_oracle):
    nrc = render_images([*AT_ORACLE, *debias(q)], SEEDS, "nrc", sun_oracle)
    assert_images_agree(nrc, pt_oracle)


def test_oracle_cache_q0_gives_the_oracle_image(pt_oracle):
    """q = 0 is the biased NRC: with the oracle at the terminal vertex it is the path tracer's mean too, and with
    a constant cache its pixels are exactly the cache's value wherever every path terminates."""
    assert_images_agree(render_images(AT_ORACLE, SEEDS, "nrc", sun_oracle), pt_oracle)


@pytest.mark.slow
@pytest.mark.parametrize("target", ["full", "indirect"])
def test_a_wrong_cache_is_unbiased_with_q_and_biased_without(target, pt_oracle):
    """The oracle x 0.5 (under ``indirect`` the cache holds the indirect light, 0 at the last vertex of this
    scene, so 0.5 x the full oracle is wrong there by its whole value): q = 0.5 agrees with the path tracer,
    q = 0 does not."""
    base = [*ORACLE, f"renderer.cache_target={target}", "renderer.termination.min_vertices=2"]
    half = scaled(0.5)
    unbiased = render_images([*base, *debias(0.5)], SEEDS, "nrc", half)
    assert_images_agree(unbiased, pt_oracle)
    biased = render_images(base, SEEDS, "nrc", half)
    with pytest.raises(AssertionError):
        assert_images_agree(biased, pt_oracle)


@pytest.mark.slow
def test_a_wrong_cache_is_unbiased_under_sun_and_sky_with_the_indirect_target():
    """The default target on sun + sky, terminating at vertex 1 into a constant (wrong) cache, q = 0.3: the image
    agrees with the path tracer to the same ``max_scatter``; q = 0 does not."""
    scene = [*ZERO, "scene.integrator.max_scatter=4"]
    pt = render_images(scene, SEEDS, "pt")
    wrong = constant(0.3)
    assert_images_agree(render_images([*scene, *debias(0.3)], SEEDS, "nrc", wrong), pt)
    with pytest.raises(AssertionError):
        assert_images_agree(render_images(scene, SEEDS, "nrc", wrong), pt)


def test_diagnostics_measure_the_cache_error_and_suffixes_train_on_the_truth():
    """With the oracle x 0.5 the measured relative cache error where render paths terminate is (L - C) / C = 1;
    the continued suffixes' training records estimate the oracle at their vertices; negative pixels are counted
    and kept (a cache ten times the truth with q = 0.5 at 1 spp gives some)."""
    cfg_overrides = ["renderer=nrc", *AT_ORACLE, *debias(0.5), "renderer.training.width=8",
                     "renderer.training.height=8", "renderer.log.tensorboard=false", "frames=1",
                     "renderer.backend=eager", "scene.integrator.spp=256"]
    cfg = compose(cfg_overrides)
    scene = load_scene(cfg.scene)
    oracle = sun_oracle(scene)
    r = make_renderer("nrc", scene, cfg, cache=StubCache(scaled(0.5)(scene)))
    pushed = []
    push = r.ring.push
    r.ring.push = lambda records, valid, *frame: (pushed.append((records, valid)), push(records, valid, *frame))[1]
    image, stats, _ = r.render_frame(0)
    assert stats["debias_continued"] > 1500
    assert 0.4 < stats["debias_continued"] / stats["debias_terminations"] < 0.6
    assert stats["debias_cache_error"] == pytest.approx(1.0, abs=0.3)  # ~4 standard deviations (3 seeds: 0.86-1.05)
    records, valid = pushed[-1]  # the suffix records come last
    assert int(valid.sum()) == stats["debias_continued"]
    truth = oracle(records.positions, records.directions)
    ratio = float(records.targets[valid].sum() / truth[valid].sum())
    assert ratio == pytest.approx(1.0, abs=0.1)

    cfg = compose([*cfg_overrides[:-1], "scene.integrator.spp=1"])
    big = make_renderer("nrc", load_scene(cfg.scene), cfg, cache=StubCache(scaled(10.0)(scene)))
    image, stats, _ = big.render_frame(0)
    assert stats["debias_negative_pixels"] > 0
    assert stats["debias_negative_pixels"] == int((image < 0).any(dim=-1).sum())


def test_debias_logs_and_metrics(tmp_path):
    cfg = compose(["renderer=nrc", *SMALL, *debias(0.5), "renderer.training.width=8", "renderer.training.height=8",
                   "frames=2", "renderer.backend=eager"])
    r = make_renderer("nrc", load_scene(cfg.scene), cfg)
    r.attach_output(tmp_path)
    m = r.render().metrics
    assert m["debias_probability"] == 0.5 and m["debias_train_on_suffixes"] is True
    assert len(m["history"]["debias_continued"]) == 2 and m["history"]["debias_continued"][0] > 0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(tmp_path / "tensorboard"))
    ea.Reload()
    assert {"debias/continued", "debias/cache_error", "debias/correction_moment"} <= set(ea.Tags()["scalars"])


@pytest.mark.parametrize("override, message", [
    ("renderer.debias.probability=1.5", "renderer.debias.probability"),
    ("renderer.debias.probability=-0.1", "renderer.debias.probability"),
    ("+renderer.debias.q=0.5", "renderer.debias: unknown key"),
])
def test_bad_debias_settings_name_the_key(override, message):
    cfg = compose(["renderer=nrc", *SMALL, override])
    with pytest.raises(ConfigError, match=message):
        make_renderer("nrc", load_scene(cfg.scene), cfg)


@pytest.mark.slow
@pytest.mark.parametrize("target", ["full", "indirect"])
def test_debias_composes_with_reservoir_reuse(target):
    """Reuse at vertex 1, where the render paths terminate: a continued path's reused estimate carries 1/q and the
    MIS under ``full``, and stays the terminal vertex's light-sampled estimate under ``indirect``; with a wrong
    cache and q = 0.5 the image agrees with the path tracer."""
    scene = [*ZERO, "scene.integrator.max_scatter=4"]
    pt = render_images(scene, SEEDS, "pt")
    nrc = render_images([*scene, f"renderer.cache_target={target}", "renderer.reuse.mode=spatial",
                         *debias(0.5)], SEEDS, "nrc", constant(0.3))
    assert_images_agree(nrc, pt)


@pytest.mark.slow
@pytest.mark.first(2)  # a cold compile of minutes: start it before the rest
def test_compiled_debias_matches_eager(fresh_machines):
    """A real compile of the debias structure (the extra random lane and P entry): the same image as its step run
    eagerly (shadow rays inside the step), and another q reuses the compiled graph (q travels in P)."""
    from nrc.render.wavefront.machine import compiled_graphs

    base = [*AT_ORACLE, *debias(0.5)]
    compiled = render_images(base, 1, "nrc", scaled(0.5), backend="compiled")
    eager = render_images(base, 1, "nrc", scaled(0.5), backend="step")
    np.testing.assert_allclose(compiled[0], eager[0], rtol=1e-4, atol=1e-6)
    graphs = compiled_graphs()  # Dynamo graphs and AOT packages built
    render_images([*AT_ORACLE, *debias(0.2)], 1, "nrc", scaled(0.5), backend="compiled")
    assert compiled_graphs() == graphs
