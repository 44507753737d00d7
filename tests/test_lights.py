"""Light sampling: lat-long mapping per SCENE.md, environment importance sampling pdf, NEE weights."""

import math

import pytest
import torch

from nrc.transport.environment import EnvironmentMap, direction_to_latlong, latlong_to_direction, uniform_sphere
from nrc.transport.light_sampling import LightSampler
from nrc.transport.lights import DirectionalLight, EnvironmentLight, PointLight


def test_latlong_mapping_follows_the_contract():
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    u, v = direction_to_latlong(d)
    torch.testing.assert_close(u[:2], torch.tensor([0.0, 0.25]))  # column 0 faces -z, a quarter turn +x
    assert float(v[2]) == pytest.approx(0.0, abs=1e-6)  # row 0 straight up
    assert float(u[3]) == pytest.approx(0.5) and float(v[3]) == pytest.approx(0.5)
    gen = torch.Generator().manual_seed(0)
    dirs = uniform_sphere(torch.rand(1000, 2, generator=gen))
    back = latlong_to_direction(*direction_to_latlong(dirs))
    torch.testing.assert_close(back, dirs, atol=1e-5, rtol=0)


@pytest.fixture
def env_map():
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(16, 32, 3, generator=gen) ** 4 * 5.0
    img[3, 7] = 200.0  # a sun-like hot pixel
    return EnvironmentMap(img, scale=0.5)


def test_env_pdf_integrates_to_one(env_map):
    gen = torch.Generator().manual_seed(2)
    d = uniform_sphere(torch.rand(400_000, 2, generator=gen))
    integral = float(env_map.pdf(d).mean()) * 4 * math.pi
    assert integral == pytest.approx(1.0, rel=0.02)


def test_env_sampling_matches_its_pdf_and_radiance_integral(env_map):
    """E[L(w)/pdf(w)] under importance sampling equals the uniform-sphere estimate of the integral."""
    gen = torch.Generator().manual_seed(3)
    n = 200_000
    d, pdf = env_map.sample(torch.rand(n, 3, generator=gen))
    # re-evaluating the pdf from the direction agrees except where rounding crosses a pixel border
    agree = torch.isclose(pdf, env_map.pdf(d), rtol=1e-3, atol=1e-6)
    assert float(agree.float().mean()) > 0.999
    is_est = env_map.radiance(d) / pdf[:, None]
    du = uniform_sphere(torch.rand(n, 2, generator=gen))
    uni_est = env_map.radiance(du) * 4 * math.pi
    for est_a, est_b in ((is_est, uni_est),):
        mean_a, mean_b = est_a.mean(0), est_b.mean(0)
        se = torch.sqrt(est_a.var(0) / n + est_b.var(0) / n)
        assert bool(((mean_a - mean_b).abs() < 4 * se).all())


def test_point_and_directional_weights():
    lights = (
        DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.tensor([1.0, 2.0, 3.0])),
        PointLight(torch.tensor([0.0, 0.0, 2.0]), torch.tensor([4.0, 4.0, 4.0])),
    )
    ls = LightSampler(lights, torch.device("cpu"))
    x = torch.zeros(2, 3)
    u = torch.tensor([[0.1, 0.5, 0.5, 0.5], [0.9, 0.5, 0.5, 0.5]])  # first -> directional, second -> point
    s = ls.sample(x, u)
    torch.testing.assert_close(s.wi, torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    torch.testing.assert_close(s.weight, torch.tensor([[2.0, 4.0, 6.0], [2.0, 2.0, 2.0]]))  # x 1/P(select) = 2
    assert math.isinf(float(s.distance[0])) and float(s.distance[1]) == pytest.approx(2.0)
    assert not bool(s.is_env.any())


def test_uniform_sky_nee_estimates_its_radiance():
    ls = LightSampler((EnvironmentLight(torch.tensor([0.2, 0.4, 0.8]), None, 2.0),), torch.device("cpu"))
    gen = torch.Generator().manual_seed(4)
    s = ls.sample(torch.zeros(10_000, 3), torch.rand(10_000, 4, generator=gen))
    assert bool(s.is_env.all())
    # weight = L / pdf = L * 4 pi for a uniform sky
    torch.testing.assert_close(s.weight[0], torch.tensor([0.4, 0.8, 1.6]) * 4 * math.pi)
    torch.testing.assert_close(s.light_pdf, torch.full((10_000,), 1 / (4 * math.pi)))


# ---------------------------------------------------------------------------- power light selection
def _hits_sphere(o: torch.Tensor, d: torch.Tensor, c: torch.Tensor, r: float) -> torch.Tensor:
    """Rays ``o + t d`` (unit ``d``, ``t > 0``) that meet the sphere ``(c, r)``."""
    oc = o - c
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - r * r)
    return (disc >= 0) & ((-b + torch.sqrt(disc.clamp(min=0))) > 0)


def test_light_powers_match_numerical_integration():
    """The power each light sends into the medium's bounding sphere (luminance): the point light's by counting
    the directions of a uniform sphere that meet it, the directional light's by a grid of parallel rays over the
    sphere's shadow square, a lat-long map of constant radiance equal to the uniform sky's."""
    from nrc.transport.light_sampling import _lum, light_powers

    c, R = torch.tensor([1.0, -2.0, 0.5]), 3.0
    gen = torch.Generator().manual_seed(11)
    sun = DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.tensor([1.0, 2.0, 3.0]))
    far = PointLight(torch.tensor([1.0, 5.0, 0.5]), torch.tensor([10.0, 20.0, 30.0]))  # 7 from c
    inside = PointLight(torch.tensor([1.0, -1.0, 0.5]), torch.tensor([1.0, 1.0, 1.0]))
    sky = EnvironmentLight(torch.tensor([0.2, 0.3, 0.4]), None, 1.5)
    sky_map = EnvironmentLight(None, torch.tensor([0.2, 0.3, 0.4]).expand(32, 64, 3).clone(), 1.5)
    p_sun, p_far, p_in, p_sky, p_map = light_powers((sun, far, inside, sky, sky_map), c, R)

    d = uniform_sphere(torch.rand(2_000_000, 2, generator=gen))
    frac = _hits_sphere(far.position.expand_as(d), d, c, R).float().mean()  # 0.048 +- 0.00015
    assert p_far == pytest.approx(_lum(far.intensity) * 4 * math.pi * float(frac), rel=0.015)
    assert p_in == pytest.approx(_lum(inside.intensity) * 4 * math.pi)
    g = torch.linspace(-R, R, 801)
    xx, zz = torch.meshgrid(g, g, indexing="ij")
    o = torch.stack([xx.reshape(-1) + c[0], torch.full((xx.numel(),), 100.0), zz.reshape(-1) + c[2]], 1)
    hit = _hits_sphere(o, sun.direction.expand_as(o), c, R).float().mean()
    assert p_sun == pytest.approx(_lum(sun.irradiance) * (2 * R) ** 2 * float(hit), rel=0.01)
    assert p_sky == pytest.approx(math.pi * R * R * 4 * math.pi * _lum(sky.radiance) * 1.5)
    assert p_map == pytest.approx(p_sky, rel=1e-3)


def test_power_selection_picks_lights_by_power_and_reweights():
    """``selection=power``: a light is chosen with probability power / total (a dark light never), its sample
    weighs 1 / P(select), and the environment's NEE pdf carries the sky's selection probability."""
    lo, hi = torch.tensor([-1.0, -1.0, -1.0]), torch.tensor([1.0, 1.0, 1.0])
    lights = (DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.tensor([3.0, 3.0, 3.0])),
              PointLight(torch.tensor([0.0, 10.0, 0.0]), torch.tensor([0.0, 0.0, 0.0])),
              EnvironmentLight(torch.tensor([0.1, 0.1, 0.1]), None, 1.0))
    ls = LightSampler(lights, torch.device("cpu"), "power", (lo, hi))
    r2 = 3.0  # the bounding sphere's radius squared
    p_sun, p_sky = math.pi * r2 * 3.0, math.pi * r2 * 4 * math.pi * 0.1
    assert ls.pmf == pytest.approx([p_sun / (p_sun + p_sky), 0.0, p_sky / (p_sun + p_sky)])
    gen = torch.Generator().manual_seed(5)
    n = 200_000
    s = ls.sample(torch.zeros(n, 3), torch.rand(n, 4, generator=gen))
    env = s.is_env.float().mean()
    assert float(env) == pytest.approx(ls.pmf[2], abs=0.005)
    sun = ~s.is_env
    assert bool((s.distance[sun] == math.inf).all())  # the dark point light (finite distance) is never chosen
    torch.testing.assert_close(s.weight[sun][0], torch.full((3,), 3.0 / ls.pmf[0]))
    torch.testing.assert_close(s.light_pdf[s.is_env], torch.full((int(s.is_env.sum()),), ls.pmf[2] / (4 * math.pi)))
    torch.testing.assert_close(ls.env_pdf(torch.tensor([[0.0, 0.0, 1.0]])), torch.tensor([ls.pmf[2] / (4 * math.pi)]))
    # the per-slot table agrees with the sampler (the same choice and weights from the same uniforms)
    from nrc.transport.light_sampling import LightTable

    table = LightTable(ls)
    assert table.structure[-1] == "power"
    u = torch.rand(1000, 4, generator=gen)
    wi, dist, weight, pdf, is_env = table.sample(table.values, tuple(torch.zeros(1000) for _ in range(3)),
                                                 [u[:, 0], u[:, 1], u[:, 2]])
    ref = ls.sample(torch.zeros(1000, 3), u)
    assert bool((is_env == ref.is_env).all())
    torch.testing.assert_close(torch.stack(weight, 1)[~is_env], ref.weight[~ref.is_env])
    torch.testing.assert_close(pdf[is_env], ref.light_pdf[ref.is_env])


def test_power_selection_without_power_is_uniform():
    lights = (DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.zeros(3)),
              PointLight(torch.tensor([0.0, 0.0, 2.0]), torch.zeros(3)))
    ls = LightSampler(lights, torch.device("cpu"), "power", (-torch.ones(3), torch.ones(3)))
    assert ls.pmf == [0.5, 0.5]
    with pytest.raises(ValueError, match="light selection must be one of"):
        LightSampler(lights, torch.device("cpu"), "stochastic")
