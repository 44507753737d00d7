"""Resampled importance sampling of lights (``renderer.light_selection=ris``): unbiased against the brute-force
sum over all lights, for every candidate count, and less noisy than its source distribution where lights differ."""

import math

import pytest
import torch

from nrc.transport.light_sampling import LightSampler, LightTable
from nrc.transport.lights import DirectionalLight, EnvironmentLight, PointLight
from nrc.transport.phase import hg_pdf
from nrc.transport.ris import resample

LO, HI = -torch.ones(3), torch.ones(3)
G = 0.6


def _lights():
    """A sun, a uniform sky and six point lights of very different strength and distance."""
    pts = [PointLight(torch.tensor(p), torch.tensor(i)) for p, i in (
        ([0.0, -3.0, 0.0], [40.0, 30.0, 20.0]), ([2.5, -2.0, 1.0], [0.5, 0.5, 2.0]), ([-3.0, -1.5, 0.5], [5.0, 1.0, 1.0]),
        ([0.3, 0.2, -0.1], [0.2, 0.3, 0.2]), ([6.0, 1.0, -4.0], [200.0, 150.0, 100.0]), ([-1.0, 4.0, 2.0], [0.0, 0.0, 0.0]))]
    return (DirectionalLight(torch.tensor([0.0, -0.8, -0.6]), torch.tensor([1.5, 1.4, 1.2])), *pts,
            EnvironmentLight(torch.tensor([0.2, 0.3, 0.5]), None, 1.0))


def _brute_force(lights, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``sum over lights`` of the unshadowed contribution at ``x`` seen from ``d`` (the sky's phase integral is 1)."""
    out = torch.zeros(3)
    for lt in lights:
        if isinstance(lt, DirectionalLight):
            out += lt.irradiance * hg_pdf(G, torch.dot(d, -lt.direction))
        elif isinstance(lt, PointLight):
            to = lt.position - x
            r2 = torch.dot(to, to)
            out += lt.intensity / r2 * hg_pdf(G, torch.dot(d, to / r2.sqrt()))
        else:
            out += lt.radiance * lt.scale
    return out


def _estimate(table: LightTable, x: torch.Tensor, d: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """``n`` next-event estimates (weight x phase, no transmittance) at ``x`` ``(3,)`` from direction ``d``."""
    gen = torch.Generator().manual_seed(seed)
    u = list(torch.rand(table.lanes, n, generator=gen).unbind(0))
    xs = tuple(torch.full((n,), float(v)) for v in x)
    ds = tuple(torch.full((n,), float(v)) for v in d)

    def phase_of(w):
        return hg_pdf(G, ds[0] * w[0] + ds[1] * w[1] + ds[2] * w[2])

    wi, dist, weight, pdf, env = table.sample_ris(table.values, xs, u, phase_of)
    return torch.stack(weight, 1) * phase_of(wi)[:, None]


@pytest.mark.parametrize("candidates", [1, 2, 8, pytest.param(32, marks=pytest.mark.slow)])
def test_ris_is_unbiased_against_the_sum_over_all_lights(candidates):
    """The mean of the RIS estimate equals the brute-force sum at three points (inside the box, near a light,
    at a corner), within 4.5 standard errors, for every ``M`` (``M = 1`` is the power selection)."""
    lights = _lights()
    table = LightTable(LightSampler(lights, torch.device("cpu"), "ris", (LO, HI), candidates))
    assert table.lanes == candidates * 3 + (candidates > 1)
    for k, (x, d) in enumerate([([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]), ([0.25, 0.1, 0.0], [1.0, 0.0, 0.0]),
                                ([0.9, -0.9, 0.9], [0.0, -1.0, 0.0])]):
        x, d = torch.tensor(x), torch.nn.functional.normalize(torch.tensor(d), dim=0)
        est = _estimate(table, x, d, 400_000, seed=10 * candidates + k)
        want = _brute_force(lights, x, d)
        err = est.std(0) / math.sqrt(len(est))
        assert bool(torch.isfinite(est).all())
        assert bool(((est.mean(0) - want).abs() < 4.5 * err + 1e-6).all()), (candidates, k, est.mean(0), want, err)


def test_ris_lowers_the_variance_of_its_source_where_lights_differ():
    """Next to one light and far from the others the unshadowed contribution, not the power, tells which light
    matters: 8 candidates have a several times lower variance than the power selection alone (``M = 1``)."""
    lights = _lights()
    x, d = torch.tensor([0.25, 0.1, 0.0]), torch.tensor([1.0, 0.0, 0.0])
    var = {}
    for m in (1, 8):
        table = LightTable(LightSampler(lights, torch.device("cpu"), "ris", (LO, HI), m))
        var[m] = float(_estimate(table, x, d, 200_000, seed=3).var(0).sum())
    assert var[8] < var[1] / 3, var


def test_resample_keeps_candidates_in_proportion_and_handles_all_dark():
    """Two delta candidates of weights 1 and 3: the second is kept 3/4 of the time, both estimates come out at the
    mean weight x 2 / M ... exactly ``sum w / M`` in luminance; all-dark candidates give a zero weight, not NaN."""
    n = 100_000
    gen = torch.Generator().manual_seed(1)
    one, zero = torch.ones(n), torch.zeros(n)

    def cand(level, k):
        return ((zero + k, zero, zero), zero + math.inf, (one * level, one * level, one * level), zero,
                torch.zeros(n, dtype=torch.bool))

    chosen, total = resample([cand(1.0, 0.0), cand(3.0, 1.0)], lambda w: torch.ones(n), torch.rand(n, generator=gen))
    assert float(chosen[0][0].mean()) == pytest.approx(0.75, abs=0.005)
    torch.testing.assert_close(chosen[2][0], torch.full((n,), 2.0))  # f(y) sum w / (M p_hat(y)) = sum w / M
    torch.testing.assert_close(total, torch.full((n,), 4.0))
    dark, total = resample([cand(0.0, 0.0), cand(0.0, 1.0)], lambda w: torch.ones(n), torch.rand(n, generator=gen))
    assert bool((dark[2][0] == 0).all()) and bool((total == 0).all())


def test_ris_under_a_latlong_map_is_unbiased():
    """The eager sampler's candidates (a lat-long map with a bright spot, and a sun): resampled by phase x
    radiance, the mean matches the quadrature of the map's radiance x phase plus the sun's term."""
    h, w = 16, 32
    img = torch.full((h, w, 3), 0.2)
    img[3:5, 8:10] = 40.0
    lights = (DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.tensor([1.0, 1.0, 1.0])),
              EnvironmentLight(None, img, 1.0))
    ls = LightSampler(lights, torch.device("cpu"), "ris", (LO, HI), 4)
    n = 400_000
    gen = torch.Generator().manual_seed(7)
    d = torch.nn.functional.normalize(torch.tensor([0.3, 0.5, -0.8]), dim=0)
    ds = tuple(torch.full((n,), float(v)) for v in d)

    def phase_of(wv):
        return hg_pdf(G, ds[0] * wv[0] + ds[1] * wv[1] + ds[2] * wv[2])

    def draw():
        s = ls.sample(torch.zeros(n, 3), torch.rand(n, 4, generator=gen))
        return tuple(s.wi.unbind(1)), s.distance, tuple(s.weight.unbind(1)), s.light_pdf, s.is_env

    chosen, _ = resample([draw() for _ in range(4)], phase_of, torch.rand(n, generator=gen))
    est = (torch.stack(chosen[2], 1) * phase_of(chosen[0])[:, None])[:, 0]
    # quadrature over the sphere (fine lat-long grid) of L(w) phase(w), plus the sun
    m = 512
    th = (torch.arange(m) + 0.5) / m * math.pi
    ph = (torch.arange(2 * m) + 0.5) / (2 * m) * 2 * math.pi
    tt, pp = torch.meshgrid(th, ph, indexing="ij")
    from nrc.transport.environment import latlong_to_direction

    dirs = latlong_to_direction((pp / (2 * math.pi)).reshape(-1), (tt / math.pi).reshape(-1))
    emap = ls.env_maps[0]
    dw = (math.pi / m) * (2 * math.pi / (2 * m)) * torch.sin(tt).reshape(-1)
    want = float((emap.radiance(dirs)[:, 0] * hg_pdf(G, dirs @ d) * dw).sum()) + float(hg_pdf(G, torch.dot(d, torch.tensor([0.0, 1.0, 0.0]))))
    err = float(est.std()) / math.sqrt(n)
    assert abs(float(est.mean()) - want) < 4.5 * err + 2e-3 * want, (float(est.mean()), want, err)


@pytest.mark.parametrize("override, message", [
    ("renderer.ris.candidates=0", "renderer.ris.candidates must be >= 1"),
    ("renderer.point_light_sampling=kulla", "renderer.point_light_sampling"),
    ("renderer.light_selection=best", "renderer.light_selection"),
    ("+renderer.ris.count=3", "renderer.ris: unknown key(s) count"),
])
def test_bad_light_sampling_settings_name_the_key(override, message):
    from conftest import compose
    from nrc.errors import ConfigError
    from nrc.render.pt import PathTracerSettings

    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        PathTracerSettings.from_config(compose(["renderer=pt", override]).renderer)


def test_light_sampling_metrics_of_a_scene():
    """Under equi-angular sampling the point lights leave the next-event choice; the entropy is log2 of the
    uniform choice's light count."""
    from conftest import compose
    from nrc.scene import load_scene
    from nrc.transport.light_sampling import LightSamplingSettings

    cfg = compose(["scene=many_lights", "scene.volume.procedural.resolution=16"])
    scene = load_scene(cfg.scene)
    both = LightSamplingSettings("uniform", 4, "none")
    m = both.metrics(both.sampler(scene))
    assert m["nee_lights"] == 17 and m["light_selection_entropy_bits"] == pytest.approx(math.log2(17))
    eq = LightSamplingSettings("ris", 4, "equiangular")
    m = eq.metrics(eq.sampler(scene))
    assert m["nee_lights"] == 1 and m["ris_candidates"] == 4 and m["light_selection_entropy_bits"] == 0.0
    assert len(eq.equiangular_points(scene)) == 16


@pytest.mark.parametrize("selection", ["uniform", "power"])
def test_light_table_looks_up_many_lights_as_the_sampler_chooses_them(selection):
    """Blocks of three or more lights of a type are looked up by index in the per-slot table: the same choice,
    directions, distances and weights as the eager sampler from the same uniforms (four suns, five points, sky)."""
    gen = torch.Generator().manual_seed(4)
    suns = tuple(DirectionalLight(torch.nn.functional.normalize(torch.randn(3, generator=gen), dim=0),
                                  torch.rand(3, generator=gen) * 3) for _ in range(4))
    pts = tuple(PointLight(torch.randn(3, generator=gen) * 4, torch.rand(3, generator=gen) * 50) for _ in range(5))
    lights = (*suns, *pts, EnvironmentLight(torch.tensor([0.1, 0.2, 0.3]), None, 1.0))
    ls = LightSampler(lights, torch.device("cpu"), selection, (LO, HI))
    table = LightTable(ls)
    n = 5000
    x = torch.randn(n, 3, generator=gen) * 0.5
    u = torch.rand(n, 4, generator=gen)
    ref = ls.sample(x, u)
    wi, dist, weight, pdf, env = table.sample(table.values, tuple(x.unbind(1)), [u[:, 0], u[:, 1], u[:, 2]])
    assert bool((env == ref.is_env).all())
    delta = ~env
    torch.testing.assert_close(torch.stack(wi, 1)[delta], ref.wi[delta])
    torch.testing.assert_close(dist[delta], ref.distance[delta])
    torch.testing.assert_close(torch.stack(weight, 1)[delta], ref.weight[delta])
    torch.testing.assert_close(pdf[env], ref.light_pdf[env])
