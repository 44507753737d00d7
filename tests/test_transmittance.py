"""Transmittance estimators: unbiasedness against quadrature, the Kettunen pieces, hard cases, the factory."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nrc.errors import ConfigError
from nrc.transport.tracking import MajorantError, TrackingStats, clip_segments
from nrc.transport.transmittance import ESTIMATORS, Transmittance, estimator_params, make_transmittance
from nrc.transport.transmittance.unbiased_raymarch import (
    roulette_probabilities,
    sample_order,
    symmetric_mean_estimate,
    tuple_size,
)
from conftest import constant_grid, hard_rays, spike_grid, unit
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import MajorantGrid

CONF = Path(__file__).resolve().parent.parent / "conf" / "transmittance"


pytestmark = pytest.mark.usefixtures("single_thread")


def ramp_grid():
    """A linear ramp along x (plus a small y slope): trilinear is exactly linear between cell centres."""
    i = torch.arange(10, dtype=torch.float32)[:, None, None]
    j = torch.arange(6, dtype=torch.float32)[None, :, None]
    D = (0.05 + 0.1 * i + 0.03 * j).expand(10, 6, 5).contiguous()
    return DensityGrid(D, center=(0, 0, 0), diagonal=3.0, density_scale=1.5)


def trilinear_grid():
    gen = torch.Generator().manual_seed(0)
    return DensityGrid(torch.rand(9, 6, 7, generator=gen) ** 2, center=(0, 0, 0), diagonal=3.0, density_scale=4.0)


GRIDS = {"constant": constant_grid, "ramp": ramp_grid, "trilinear": trilinear_grid}


def segments(grid):
    """Three segments: a full crossing from outside, a partial [t0, t1] one, and one from inside to the exit."""
    c, ext = grid.box.center, grid.box.extent
    o = torch.stack([c - ext * torch.tensor([0.9, 0.3, 0.2]), c + ext * torch.tensor([0.1, 0.9, -0.2]), c + 0.1 * ext])
    d = unit(torch.tensor([[1.0, 0.3, 0.25], [-0.1, -1.0, 0.15], [0.4, -0.3, -0.6]]))
    _, a, b = clip_segments(grid, o, d, None, None)
    t0 = torch.stack([torch.tensor(0.0), a[1] + 0.2 * (b[1] - a[1]), torch.tensor(0.0)])
    t1 = torch.stack([torch.tensor(math.inf), a[1] + 0.8 * (b[1] - a[1]), torch.tensor(math.inf)])
    return o, d, t0, t1


def exact_transmittance(grid, o, d, t0, t1, n=40001):
    """T of each segment by fine trapezoid quadrature of sigma_t (float64 accumulation)."""
    oc, a, b = clip_segments(grid, o, d, t0, t1)
    out = []
    for r in range(o.shape[0]):
        if not b[r] > a[r]:
            out.append(1.0)
            continue
        t = torch.linspace(float(a[r]), float(b[r]), n, dtype=torch.float64)
        x = oc[r].double()[None] + t[:, None] * d[r].double()[None]
        s = grid.sigma_t(x.float()).double()
        out.append(math.exp(-float(torch.trapezoid(s, t))))
    return torch.tensor(out, dtype=torch.float64)


UNBIASED = [
    ("ratio", {"majorant": "global"}),
    ("ratio", {"majorant": "brick"}),
    ("ratio", {"majorant": "brick", "roulette_threshold": 0.0}),
    ("residual_ratio", {}),
    ("residual_ratio", {"roulette_threshold": 0.2}),
    ("track_length", {"majorant": "global"}),
    ("track_length", {"majorant": "brick"}),
    ("unbiased_raymarch", {}),
]


@pytest.mark.parametrize("which", list(GRIDS))
@pytest.mark.parametrize("name,params", UNBIASED, ids=[f"{n}-{'-'.join(map(str, p.values()))}" for n, p in UNBIASED])
def test_unbiased_estimators_match_quadrature(which, name, params):
    grid = GRIDS[which]()
    mg = MajorantGrid(grid, brick=2)
    o, d, t0, t1 = segments(grid)
    exact = exact_transmittance(grid, o, d, t0, t1)
    if which == "constant":  # analytic
        _, a, b = clip_segments(grid, o, d, t0, t1)
        exact = torch.exp(-0.8 * (b - a).double())
    n = 4000
    rep = lambda x: x.repeat_interleave(n, 0)  # noqa: E731
    T, st = ESTIMATORS[name](grid, mg, rep(o), rep(d), rep(t0), rep(t1), torch.Generator().manual_seed(123),
                             return_stats=True, **params)
    assert T.dtype == torch.float32 and T.shape == (3 * n,)
    assert torch.isfinite(T).all()
    assert isinstance(st, TrackingStats) and st.rays == 3 * n
    T = T.view(3, n).double()
    mean, se = T.mean(dim=1), T.std(dim=1) / math.sqrt(n)
    tol = 4 * se + 2e-5 + 1e-4 * exact
    assert bool(((mean - exact).abs() < tol).all()), (mean, exact, se)
    if name in ("ratio", "biased_raymarch", "track_length"):
        assert bool((T >= 0).all() and (T <= 1).all())
    if which == "constant" and name in ("residual_ratio", "unbiased_raymarch"):
        # zero variance for constant density (residual: sigma_t == control; Kettunen: exact combs)
        assert float((T.std(dim=1) / exact).max()) < 1e-5


def test_unbiased_raymarch_zero_variance_on_constant_density_and_one_comb():
    grid = constant_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d, t0, t1 = segments(grid)
    n = 3000
    T, st = ESTIMATORS["unbiased_raymarch"](grid, mg, o.repeat(n, 1), d.repeat(n, 1), t0.repeat(n), t1.repeat(n),
                                            torch.Generator().manual_seed(0), return_stats=True)
    _, a, b = clip_segments(grid, o, d, t0, t1)
    exact = torch.exp(-0.8 * (b - a)).repeat(n)
    torch.testing.assert_close(T, exact, rtol=2e-6, atol=0)
    # tau_c = 0 (majorant == minorant on every brick) => M = 1 comb sample per order
    assert st.lookups < 1.5 * 3 * n


def test_biased_raymarch_is_biased_upwards_and_the_bias_shrinks_with_m():
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d, t0, t1 = segments(grid)
    o, d, t0, t1 = o[:1], d[:1], t0[:1], t1[:1]
    exact = float(exact_transmittance(grid, o, d, t0, t1)[0])
    n = 12000
    bias, ses = {}, {}
    for m in (1, 2, 4, 16):
        T = ESTIMATORS["biased_raymarch"](grid, mg, o.expand(n, 3), d.expand(n, 3), t0.expand(n), t1.expand(n),
                                          torch.Generator().manual_seed(m), m=m).double()
        assert bool((T >= 0).all() and (T <= 1).all())
        bias[m], ses[m] = float(T.mean()) - exact, float(T.std()) / math.sqrt(n)
    assert bias[1] > 10 * ses[1]  # clearly biased upwards
    assert bias[2] > 4 * ses[2]
    assert bias[1] > bias[2] > bias[4] and abs(bias[16]) < bias[4]
    assert bias[16] > -4 * ses[16]
    # step-size and automatic M work too, and the automatic M's bias is small
    for params in ({"step": 0.05}, {}):
        T = ESTIMATORS["biased_raymarch"](grid, mg, o.expand(n, 3), d.expand(n, 3), t0.expand(n), t1.expand(n),
                                          torch.Generator().manual_seed(5), **params).double()
        assert abs(float(T.mean()) - exact) < 0.02 * exact


def test_roulette_probabilities_and_order_sampling():
    p = roulette_probabilities(10)
    torch.testing.assert_close(p[:6], torch.tensor([1.0, 0.1, 0.1, 0.2 / 3, 0.1 / 3, 0.04 / 3], dtype=torch.float64))
    assert float(p[1:].sum()) == pytest.approx(0.31945, abs=2e-5)  # E[N]
    n = 400_000
    N = sample_order(torch.rand(n, generator=torch.Generator().manual_seed(0)), p)
    assert int(N.max()) <= 10 and not bool((N == 1).any())
    for k, pk in enumerate([1.0, 0.1, 0.1, 0.0667, 0.0333]):
        emp = float((N >= k).double().mean())
        se = math.sqrt(max(pk * (1 - pk), 1e-12) / n)
        assert abs(emp - pk) < 4 * se + 5e-5, (k, emp, pk)
    # truncation
    assert int(sample_order(torch.full((4,), 0.0), roulette_probabilities(3)).max()) == 3


def test_tuple_size_table():
    M = tuple_size(torch.tensor([0.0, 1.0, 5.0, 20.0, 100.0]), max_m=1024)
    assert M.tolist() == [1, 4, 10, 25, 89]
    assert int(tuple_size(torch.tensor([1e6]), max_m=64)) == 64


def test_symmetric_means_divide_by_the_order_probabilities():
    p = roulette_probabilities(10).float()
    X = torch.tensor([[0.7, 1.1, 0.4, 0.0], [0.9, 1.3, 0.2, 0.5]])
    order = torch.tensor([2, 3])
    got = symmetric_mean_estimate(X, order, p.double())
    P = p.double()
    # by hand: pivot i, values d_j = X_i - X_j (j != i, j <= N), m_k = mean of k-products
    from itertools import combinations

    for r in range(2):
        N = int(order[r])
        x = X[r, : N + 1].double()
        total = 0.0
        for i in range(N + 1):
            dv = [float(x[i] - x[j]) for j in range(N + 1) if j != i]
            s = 0.0
            for k in range(N + 1):
                combs = list(combinations(dv, k))
                mk = sum(math.prod(c) for c in combs) / len(combs)
                s += mk / (math.factorial(k) * float(P[k]))
            total += math.exp(-float(x[i])) * s
        assert float(got[r]) == pytest.approx(total / (N + 1), rel=1e-12)





HARD = {
    "scale0": lambda: DensityGrid(torch.rand(5, 4, 6), center=(0, 0, 0), diagonal=2.0, density_scale=0.0),
    "scale1e4": lambda: DensityGrid(torch.rand(5, 4, 6), center=(0, 0, 0), diagonal=2.0, density_scale=1e4),
    "empty": lambda: DensityGrid(torch.zeros(5, 4, 6), center=(0, 0, 0), diagonal=2.0, density_scale=1.0),
    "spike": spike_grid,
}


@pytest.mark.parametrize("which", list(HARD))
@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_hard_cases_are_finite_and_terminate(which, name):
    grid = HARD[which]()
    mg = MajorantGrid(grid, brick=2)
    o, d = hard_rays(grid)
    reps = 40
    O, Dd = o.repeat(reps, 1), d.repeat(reps, 1)
    T = ESTIMATORS[name](grid, mg, O, Dd, None, None, torch.Generator().manual_seed(1))
    assert torch.isfinite(T).all()
    T = T.view(reps, -1)
    assert bool((T[:, 6:] == 1).all())  # misses
    if which in ("scale0", "empty"):
        assert bool((T == 1).all())
    if which == "scale1e4":
        assert abs(float(T[:, 0].mean())) < 1e-3  # opaque from the centre
    if which == "spike":
        # the segment through the spike's centre along +y from the top: exact T by quadrature
        ex = float(exact_transmittance(grid, o[5:6], d[5:6], torch.zeros(1), torch.full((1,), math.inf))[0])
        Ts = T[:, 5].double()
        assert abs(float(Ts.mean()) - ex) < 4 * float(Ts.std()) / math.sqrt(reps) + 0.02


@pytest.mark.parametrize("name", ["ratio", "residual_ratio", "track_length"])
def test_tracking_estimators_check_the_majorant(name):
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    mg.majorant.mul_(0.5)
    mg.global_majorant *= 0.5
    o, d, t0, t1 = segments(grid)
    with pytest.raises(MajorantError):
        ESTIMATORS[name](grid, mg, o.repeat(300, 1), d.repeat(300, 1), t0.repeat(300), t1.repeat(300),
                         torch.Generator().manual_seed(0))


def test_same_seed_same_result_and_scalar_segments():
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d, _, _ = segments(grid)
    for name in ESTIMATORS:
        a = ESTIMATORS[name](grid, mg, o.repeat(50, 1), d.repeat(50, 1), 0.1, 2.0, torch.Generator().manual_seed(9))
        b = ESTIMATORS[name](grid, mg, o.repeat(50, 1), d.repeat(50, 1), 0.1, 2.0, torch.Generator().manual_seed(9))
        assert torch.equal(a, b), name


def test_configs_and_factory():
    names = set()
    for f in sorted(CONF.glob("*.yaml")):
        cfg = OmegaConf.load(f)
        est = make_transmittance(cfg)
        assert isinstance(est, Transmittance) and est.name == f.stem
        assert set(est.params) == set(estimator_params(est.name)) - {"return_stats"}, f.name
        names.add(est.name)
    assert names == set(ESTIMATORS)
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d, t0, t1 = segments(grid)
    est = make_transmittance({"name": "ratio", "majorant": "global", "roulette_threshold": 0.0})
    T, st = est(grid, mg, o, d, t0, t1, torch.Generator().manual_seed(0), return_stats=True)
    assert T.shape == (3,) and st.lookups > 0
    assert make_transmittance(None).name == "ratio"
    with pytest.raises(ConfigError, match="transmittance.name"):
        make_transmittance({"name": "nope"})
    with pytest.raises(ConfigError, match="transmittance.bogus"):
        make_transmittance({"name": "ratio", "bogus": 1})


def test_relative_efficiency_on_a_varying_density():
    """Variance x lookups ordering of ALGORITHMS.md on rays through the random trilinear grid:
    Kettunen < residual ratio < ratio < track length (see docs/transmittance.md for the numbers)."""
    grid = trilinear_grid()
    mg = MajorantGrid(grid, brick=2)
    o, d, t0, t1 = segments(grid)
    n = 3000
    rep = lambda x: x.repeat_interleave(n, 0)  # noqa: E731
    cost = {}
    for name, params in [("unbiased_raymarch", {}), ("residual_ratio", {}), ("ratio", {"roulette_threshold": 0.0}),
                         ("track_length", {})]:
        T, st = ESTIMATORS[name](grid, mg, rep(o), rep(d), rep(t0), rep(t1), torch.Generator().manual_seed(2),
                                 return_stats=True, **params)
        var = T.double().view(3, n).var(dim=1).mean()
        cost[name] = float(var) * st.lookups / (3 * n)
    assert cost["unbiased_raymarch"] < cost["residual_ratio"] < cost["ratio"] < cost["track_length"]
    assert np.isfinite(list(cost.values())).all()


PLUGIN = '''"""A test's transmittance estimator: ratio tracking times a factor."""
from nrc.transport.transmittance import ratio


def estimate(grid, majorants, origin, direction, t0, t1, gen, scale=1.0, return_stats=False):
    out = ratio.estimate(grid, majorants, origin, direction, t0, t1, gen, return_stats=return_stats)
    return (out[0] * scale, out[1]) if return_stats else out * scale
'''


def test_a_new_estimator_is_one_file_and_one_yaml(tmp_path, monkeypatch):
    """A module and a YAML (``estimator: module:function``) add an estimator that ``pt`` renders with: factor 1
    reproduces ratio tracking's image exactly (the same draws on the queued shadow rays), factor 0 leaves the
    environment alone."""
    from nrc.config import compose
    from nrc.render.registry import make_renderer
    from nrc.scene import load_scene

    (tmp_path / "plugin_estimator.py").write_text(PLUGIN)
    (tmp_path / "scaled_ratio.yaml").write_text("name: scaled_ratio\nestimator: plugin_estimator:estimate\n"
                                                "scale: 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    small = ["renderer=pt", "renderer.backend=eager", "scene.volume.procedural.resolution=16",
             "scene.camera.width=24", "scene.camera.height=14", "scene.integrator.spp=2"]

    def render(transmittance):
        cfg = compose(small)
        cfg.transmittance = transmittance
        return make_renderer("pt", load_scene(cfg.scene), cfg).render().image

    plugin = OmegaConf.load(tmp_path / "scaled_ratio.yaml")
    try:
        same = render(plugin)
        plugin.scale = 0.0
        dark = render(plugin)
        reference = render(OmegaConf.create({"name": "ratio"}))
    finally:
        ESTIMATORS.pop("scaled_ratio", None)
    assert np.array_equal(same, reference)
    assert dark.mean() < 0.9 * reference.mean()


@pytest.mark.parametrize("spec, words", [("no_colon", "module:function"),
                                         ("no_such_module_x:estimate", "cannot be imported"),
                                         ("math:sqrt", "lacks the parameter")])
def test_a_bad_estimator_entry_is_one_line(spec, words):
    with pytest.raises(ConfigError, match=words):
        make_transmittance({"name": "bad_one", "estimator": spec})
    assert "bad_one" not in ESTIMATORS
