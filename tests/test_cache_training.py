"""Loss, EMA, optimiser groups, NaN guards and checkpoints of the radiance cache."""

import io
import math

import pytest
import torch
from torch import nn

from nrc.cache import RadianceCache, build_radiance_cache
from nrc.cache.ema import WeightEMA
from nrc.cache.encodings.hashgrid import HashGridEncoding
from nrc.cache.loss import relative_l2_luminance
from nrc.volume.grid import DensityGrid

CACHE = {
    "network": {"n_neurons": 32, "n_hidden_layers": 3, "bf16": False},
    "optimizer": {"lr": 1e-2, "eps": 1e-15, "weight_decay": 1e-6},
    "ema": {"alpha": 0.99},
    "loss": {"target_clamp": 100.0},
    "query_chunk": 100,
}
HASH_ONEBLOB = {
    "position": {"otype": "HashGrid", "n_levels": 4, "n_features_per_level": 2, "log2_hashmap_size": 10,
                 "base_resolution": 4, "per_level_scale": 2.0},
    "direction": {"otype": "OneBlob", "n_bins": 4},
}


def _grid() -> DensityGrid:
    return DensityGrid(torch.rand(8, 6, 5, generator=torch.Generator().manual_seed(0)), center=(0, 0, 0),
                       diagonal=2.0, density_scale=1.0)


def _cache(grid=None, seed=0, cache=CACHE, encoding=HASH_ONEBLOB, extras=None) -> RadianceCache:
    return build_radiance_cache(cache, encoding, extras or {}, grid or _grid(), "cpu", seed)


def _batch(grid: DensityGrid, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    lo, hi = grid.box.lo, grid.box.hi
    x = lo + (hi - lo) * torch.rand(n, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return x, d


# ---------------------------------------------------------------- loss
def test_loss_matches_hand_computation():
    p = torch.tensor([[1.0, 2.0, 0.5], [0.0, 0.0, 0.0]])
    t = torch.tensor([[0.5, 2.5, 1.0], [1.0, 0.0, 2.0]])
    y0 = 0.299 * 1.0 + 0.587 * 2.0 + 0.114 * 0.5  # 1.53
    row0 = (0.25 + 0.25 + 0.25) / (y0**2 + 0.01)
    row1 = (1.0 + 0.0 + 4.0) / 0.01
    loss = relative_l2_luminance(p, t, target_clamp=10.0)
    assert loss.item() == pytest.approx((row0 + row1) / 2, rel=1e-6)


def test_loss_gradient_treats_denominator_as_constant():
    p = torch.tensor([[1.0, 2.0, 0.5], [0.3, 0.1, 0.2]], requires_grad=True)
    t = torch.tensor([[0.5, 2.5, 1.0], [1.0, 0.0, 2.0]])
    relative_l2_luminance(p, t, target_clamp=10.0).backward()
    lum = (p.detach() * torch.tensor([0.299, 0.587, 0.114])).sum(dim=1, keepdim=True)
    expected = 2.0 * (p.detach() - t) / (lum**2 + 0.01) / 2
    torch.testing.assert_close(p.grad, expected)


def test_loss_scale_floor_adds_the_batch_mean_target_luminance_to_the_denominator():
    p = torch.tensor([[1.0, 2.0, 0.5], [0.0, 0.0, 0.0]])
    t = torch.tensor([[0.5, 2.5, 1.0], [1.0, 0.0, 2.0]])
    y0 = 0.299 * 1.0 + 0.587 * 2.0 + 0.114 * 0.5
    mean_t = ((0.299 * 0.5 + 0.587 * 2.5 + 0.114 * 1.0) + (0.299 * 1.0 + 0.114 * 2.0)) / 2
    floor = (0.5 * mean_t) ** 2
    expected = (0.75 / (y0**2 + 0.01 + floor) + 5.0 / (0.01 + floor)) / 2
    assert relative_l2_luminance(p, t, 10.0, scale_floor=0.5).item() == pytest.approx(expected, rel=1e-6)
    assert relative_l2_luminance(p, t, 10.0, scale_floor=0.0).item() == relative_l2_luminance(p, t, 10.0).item()
    # an untrained cache (predictions 0): with a large floor every sample weighs alike, as in a plain L2
    zero = torch.zeros(2, 3, requires_grad=True)
    relative_l2_luminance(zero, t * 1e3, 1e6, scale_floor=100.0).backward()
    torch.testing.assert_close(zero.grad / zero.grad.abs().max(), -t / t.abs().max(), rtol=1e-4, atol=1e-6)


def test_loss_relative_clamp_scales_targets_above_k_times_the_prediction_or_the_batch_mean():
    p = torch.zeros(4, 3)
    t = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [9.0, 18.0, 9.0]])  # luminances 1, 1, 1, 14.4
    mean = (3.0 + 0.299 * 9 + 0.587 * 18 + 0.114 * 9) / 4  # 4.35
    cap = 2.0 * mean
    clamped = t.clone()
    clamped[3] *= cap / (0.299 * 9 + 0.587 * 18 + 0.114 * 9)  # scaled down, its colour kept
    want = relative_l2_luminance(p, clamped, 100.0)
    assert relative_l2_luminance(p, t, 100.0, relative_clamp=2.0).item() == pytest.approx(want.item(), rel=1e-6)
    # where the cache predicts more than the batch's mean, the cap is k times its own prediction
    bright = torch.zeros(4, 3)
    bright[3] = 5.0  # luminance 5 > the mean 4.35: cap 2 x 5 = 10
    capped = t.clone()
    capped[3] *= 10.0 / (0.299 * 9 + 0.587 * 18 + 0.114 * 9)
    assert relative_l2_luminance(bright, t, 100.0, relative_clamp=2.0).item() == pytest.approx(
        relative_l2_luminance(bright, capped, 100.0).item(), rel=1e-6)
    # clamp_to=mean: k times the batch's mean for every target, whatever the prediction
    assert relative_l2_luminance(bright, t, 100.0, relative_clamp=2.0, clamp_to="mean").item() == pytest.approx(
        relative_l2_luminance(bright, clamped, 100.0).item(), rel=1e-6)
    # below the cap nothing changes; 0 turns it off
    assert relative_l2_luminance(p, t, 100.0, relative_clamp=4.0).item() == relative_l2_luminance(p, t, 100.0).item()
    assert relative_l2_luminance(p, t, 100.0, relative_clamp=0.0).item() == relative_l2_luminance(p, t, 100.0).item()


def test_loss_clamp_excess_spread_gives_the_clamped_luminance_back_to_the_batch():
    p = torch.zeros(5, 3)
    t = torch.tensor([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [1.0, 1.0, 1.0], [9.0, 18.0, 9.0], [-0.5, -0.5, -0.5]])
    lum = t @ torch.tensor([0.299, 0.587, 0.114])  # 1, 2, 1, 14.4, -0.5
    cap = 2.0 * lum.mean()  # the prediction is 0: k x the batch's mean, 7.16
    clamped = t.clone()
    clamped[3] *= cap / lum[3]
    removed = lum[3] - cap
    gain = 1.0 + removed / (1.0 + 2.0 + 1.0 + cap)  # over the positive targets' clamped luminance
    spread = clamped.clone()
    spread[:4] *= gain  # the negative target is left as it is
    assert (spread[:4] @ torch.tensor([0.299, 0.587, 0.114])).sum().item() == pytest.approx(lum[:4].sum().item())
    got = relative_l2_luminance(p, t, 100.0, relative_clamp=2.0, clamp_excess="spread")
    assert got.item() == pytest.approx(relative_l2_luminance(p, spread, 100.0).item(), rel=1e-6)
    # the bright target stays below its own luminance: spreading is not undoing the clamp
    assert gain.item() * cap.item() < lum[3].item()
    # nothing above the cap: spread changes nothing
    assert relative_l2_luminance(p[:3], t[:3], 100.0, relative_clamp=2.0, clamp_excess="spread").item() == pytest.approx(
        relative_l2_luminance(p[:3], t[:3], 100.0).item(), rel=1e-7)


def test_loss_clamps_targets_and_handles_empty_batch():
    p = torch.tensor([[1.0, 1.0, 1.0]])
    huge = relative_l2_luminance(p, torch.tensor([[1e30, float("inf"), 5.0]]), target_clamp=8.0)
    assert huge.item() == pytest.approx(relative_l2_luminance(p, torch.tensor([[8.0, 8.0, 5.0]]), 8.0).item())
    empty = torch.zeros(0, 3, requires_grad=True)
    loss = relative_l2_luminance(empty, torch.zeros(0, 3), target_clamp=8.0)
    assert loss.item() == 0.0 and not torch.isnan(loss)
    loss.backward()
    assert empty.grad.shape == (0, 3)


# ---------------------------------------------------------------- EMA
def test_ema_follows_debiased_recursion():
    model = nn.Linear(1, 1, bias=False)
    alpha = 0.9
    ema = WeightEMA(model, alpha)
    ws = [3.0, -1.0, 2.5, 0.0, 7.0, 1.0]
    expected, mu_prev = 0.0, 0.0
    for k, w in enumerate(ws, start=1):
        with torch.no_grad():
            model.weight.fill_(w)
        ema.update()
        mu = 1.0 - alpha**k
        expected = (alpha * mu_prev * expected + (1.0 - alpha) * w) / mu  # thesis eq. 4.3
        mu_prev = mu
        assert ema.shadow.weight.item() == pytest.approx(expected, rel=1e-6, abs=1e-6)
        if k == 1:
            assert ema.shadow.weight.item() == pytest.approx(w)  # debiased: no pull towards zero
    assert model.weight.item() == ws[-1]  # the raw weights are untouched


def test_ema_window_fraction_bounds_the_average_to_recent_steps():
    model = nn.Linear(1, 1, bias=False)
    plain, young = WeightEMA(model, 0.99), WeightEMA(model, 0.99, window_fraction=0.25)
    assert [young.rate(k) for k in (1, 5)] == [1.0, pytest.approx(0.5)]  # 1 / (1 + f (k - 1))
    assert young.rate(2000) == pytest.approx(plain.rate(2000))  # window at 1/(1-alpha): the plain EMA
    assert all(young.rate(k) >= plain.rate(k) for k in range(1, 3000))
    assert WeightEMA(model, 0.99, window_fraction=1.0).rate(7) == pytest.approx(plain.rate(7))
    for ema in (plain, young):  # 40 steps of 0 then 40 of 1: the windowed average has forgotten the zeros
        for k in range(80):
            with torch.no_grad():
                model.weight.fill_(float(k >= 40))
            ema.update()
    assert plain.shadow.weight.item() == pytest.approx((1 - 0.99**40) / (1 - 0.99**80), rel=1e-5)  # ~0.60
    # prod over k = 41..80 of (1 - 1 / (1 + (k - 1) / 4)) = 40*41*42*43 / (80*81*82*83): ~0.067 of the zeros left
    assert young.shadow.weight.item() == pytest.approx(1 - 40 * 41 * 42 * 43 / (80 * 81 * 82 * 83), rel=1e-5)
    with pytest.raises(ValueError, match="window_fraction"):
        WeightEMA(model, 0.99, window_fraction=0.0)


def test_ema_hold_window_is_shorter_while_the_rate_is_held_then_grows():
    """``hold_fraction`` replaces the window fraction for the first ``hold`` steps; after them the rate is the
    window's own (the lerp's state kept), so the held EMA forgets the early zeros faster and ends where the plain
    windowed one would be from its state."""
    model = nn.Linear(1, 1, bias=False)
    held = WeightEMA(model, 0.99, window_fraction=0.5, hold=8, hold_fraction=0.25)
    plain = WeightEMA(model, 0.99, window_fraction=0.5)
    assert [held.rate(k) for k in (1, 5, 8)] == [1.0, pytest.approx(0.5), pytest.approx(1 / 2.75)]
    assert [held.rate(k) for k in (9, 200)] == [pytest.approx(plain.rate(9)), pytest.approx(plain.rate(200))]
    assert WeightEMA(model, 0.99, 0.5, hold=8).rate(5) == pytest.approx(plain.rate(5))  # no hold fraction: f
    for ema in (held, plain):  # 4 steps of 0, 4 of 1, then 4 of 1 again
        for k in range(12):
            with torch.no_grad():
                model.weight.fill_(float(k >= 4))
            ema.update()
    zeros = lambda f, ks: math.prod(1 - 1 / (1 + f * (k - 1)) for k in ks)  # noqa: E731  (what is left of them)
    assert held.shadow.weight.item() == pytest.approx(1 - zeros(0.25, range(5, 9)) * zeros(0.5, range(9, 13)))
    assert plain.shadow.weight.item() == pytest.approx(1 - zeros(0.5, range(5, 13)))
    assert held.shadow.weight.item() > plain.shadow.weight.item()
    with pytest.raises(ValueError, match="hold_window_fraction"):
        WeightEMA(model, 0.99, 0.5, hold=8, hold_fraction=1.5)


def test_ema_weights_serve_queries_and_raw_weights_train():
    grid = _grid()
    cache = _cache(grid)
    x, d = _batch(grid, 64, 1)
    raw_before = [p.detach().clone() for p in cache.network.parameters()]
    for _ in range(3):
        cache.train_step(x, d, torch.ones(64, 3))
    assert cache.n_steps == 3 and cache.ema.step == 3
    assert any(not torch.equal(a, b) for a, b in zip(raw_before, cache.network.parameters()))
    with torch.no_grad():
        raw_pred = cache.network(cache.inputs(x, d))
        ema_pred = cache.ema.shadow(cache.inputs(x, d))
    q = cache.query(x, d)
    torch.testing.assert_close(q, ema_pred)
    assert not torch.allclose(q, raw_pred)
    torch.testing.assert_close(cache.query_raw(x, d), raw_pred)  # the self-training queries' option


# ---------------------------------------------------------------- optimiser
def test_adam_groups_follow_tcnn_conventions():
    cache = _cache()
    groups = cache.optimizer.param_groups
    assert len(groups) == 2
    mlp, table = groups
    assert mlp["params"] == list(cache.network.mlp.parameters())
    assert (mlp["lr"], mlp["eps"], mlp["weight_decay"]) == (1e-2, 1e-15, 1e-6)
    hashgrid = cache.network.encoding.encodings[0]
    assert isinstance(hashgrid, HashGridEncoding) and table["params"] == [hashgrid.table]
    assert (table["lr"], table["eps"], table["weight_decay"]) == (1e-2, 1e-15, 0.0)
    assert all(g["betas"] == (0.9, 0.99) for g in groups)


def test_lazy_adam_moves_touched_columns_as_adam_and_leaves_the_rest():
    from nrc.cache.optim import LazyAdam

    torch.manual_seed(0)
    init = torch.randn(2, 6)
    lazy_p, dense_p = nn.Parameter(init.clone()), nn.Parameter(init.clone())
    lazy = LazyAdam([lazy_p], lr=0.1, betas=(0.9, 0.99), eps=1e-15)
    dense = torch.optim.Adam([dense_p], lr=0.1, betas=(0.9, 0.99), eps=1e-15)
    for k in range(3):  # columns 0-3 touched every step: Adam exactly; 4, 5 never: untouched
        g = torch.zeros(2, 6)
        g[:, :4] = torch.randn(2, 4)
        lazy_p.grad, dense_p.grad = g.clone(), g.clone()
        lazy.step()
        dense.step()
    torch.testing.assert_close(lazy_p[:, :4], dense_p[:, :4])
    assert torch.equal(lazy_p[:, 4:], init[:, 4:])
    # a column touched once after others took 3 steps: its own step count (1) sets its bias correction
    g = torch.zeros(2, 6)
    g[:, 5] = 1.0
    lazy_p.grad = g
    before = lazy_p.detach().clone()
    lazy.step()
    assert lazy.state[lazy_p]["step"].tolist() == [3, 3, 3, 3, 0, 1]
    torch.testing.assert_close(lazy_p[:, 5], before[:, 5] - 0.1)  # first Adam step: lr * sign(g)
    assert torch.equal(lazy_p[:, :5], before[:, :5])


def test_lazy_hash_table_cache_trains_and_resumes_exactly():
    enc = {**HASH_ONEBLOB, "position": {**HASH_ONEBLOB["position"], "lazy": True}}
    grid = _grid()
    a = build_radiance_cache(CACHE, enc, {}, grid, "cpu", seed=3)
    assert len(a.optimizer.param_groups) == 2
    torch.manual_seed(1)
    x, d, t = torch.rand(256, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(256, 3), dim=1), torch.rand(256, 3)
    for _ in range(3):
        a.train_step(x, d, t)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)  # as a checkpoint
    buf.seek(0)
    b = build_radiance_cache(CACHE, enc, {}, grid, "cpu", seed=3)
    b.load_state_dict(torch.load(buf, weights_only=True))
    a.train_step(x, d, t)
    b.train_step(x, d, t)
    for pa, pb in zip(a.network.parameters(), b.network.parameters()):
        assert torch.equal(pa, pb)


# ---------------------------------------------------------------- robustness
def test_no_nan_with_zero_huge_and_empty_targets():
    grid = _grid()
    cache = _cache(grid)
    x, d = _batch(grid, 128, 2)
    assert math.isfinite(cache.train_step(x, d, torch.zeros(128, 3)))
    huge = torch.full((128, 3), 1e30)
    huge[0, 0] = float("inf")
    assert math.isfinite(cache.train_step(x, d, huge))
    assert cache.train_step(x[:0], d[:0], torch.zeros(0, 3)) == 0.0
    assert cache.n_steps == 2 and cache.n_skipped_steps == 0
    assert all(torch.isfinite(p).all() for p in cache.network.parameters())
    assert torch.isfinite(cache.query(x, d)).all()
    assert cache.query(x[:0], d[:0]).shape == (0, 3)


def test_non_finite_loss_or_gradient_skips_the_step():
    grid = _grid()
    cache = _cache(grid)
    x, d = _batch(grid, 32, 3)
    cache.train_step(x, d, torch.ones(32, 3))
    before = {k: v.clone() for k, v in cache.state_dict()["network"].items()}
    ema_before = cache.ema.shadow.mlp.layers[0].weight.clone()
    nan_targets = torch.ones(32, 3)
    nan_targets[5, 1] = float("nan")
    assert math.isnan(cache.train_step(x, d, nan_targets))
    handle = cache.network.mlp.layers[1].weight.register_hook(lambda g: torch.full_like(g, float("inf")))
    assert math.isfinite(cache.train_step(x, d, torch.ones(32, 3)))  # finite loss, infinite gradient
    handle.remove()
    assert cache.n_skipped_steps == 2 and cache.n_steps == 1 and cache.ema.step == 1
    for k, v in cache.state_dict()["network"].items():
        assert torch.equal(v, before[k]), k
    assert torch.equal(cache.ema.shadow.mlp.layers[0].weight, ema_before)
    assert math.isfinite(cache.train_step(x, d, torch.ones(32, 3))) and cache.n_steps == 2


def test_mlp_learning_rate_schedule_falls_towards_its_final_fraction_and_leaves_the_tables():
    decay = {**CACHE, "optimizer": {**CACHE["optimizer"], "lr_final_fraction": 0.25, "lr_half_life": 2.0}}
    grid = _grid()
    cache = _cache(grid, cache=decay)
    assert [cache.settings.mlp_lr_factor(k) for k in (0, 2, 4)] == [1.0, 0.625, 0.4375]
    assert cache.settings.mlp_lr_factor(10_000) == pytest.approx(0.25)
    held = _cache(grid, cache={**decay, "optimizer": {**decay["optimizer"], "lr_hold": 3}})  # the full rate for 3 steps
    assert [held.settings.mlp_lr_factor(k) for k in (0, 3, 5, 7)] == [1.0, 1.0, 0.625, 0.4375]
    mlp, table = cache.optimizer.param_groups
    for k in range(5):
        x, d = _batch(grid, 32, k)
        cache.train_step(x, d, torch.rand(32, 3, generator=torch.Generator().manual_seed(k)))
        assert mlp["lr"] == pytest.approx(1e-2 * (0.25 + 0.75 * 0.5 ** (k / 2)))  # the lr of step k
        assert table["lr"] == 1e-2
    constant = _cache(grid)
    assert all(constant.settings.mlp_lr_factor(k) == 1.0 for k in (0, 7, 10_000))
    # the schedule changes training: the same batches give other weights than the constant rate
    a, b = _cache(grid, cache=decay), _cache(grid)
    for k in range(6):
        x, d = _batch(grid, 32, k)
        t = torch.rand(32, 3, generator=torch.Generator().manual_seed(k))
        a.train_step(x, d, t), b.train_step(x, d, t)
    xq, dq = _batch(grid, 50, 99)
    assert not torch.equal(a.query_raw(xq, dq), b.query_raw(xq, dq))


def test_learning_rate_schedule_resumes_exactly():
    decay = {**CACHE, "optimizer": {**CACHE["optimizer"], "lr_final_fraction": 0.3, "lr_half_life": 1.5}}
    grid = _grid()
    batches = [(*_batch(grid, 48, k), torch.rand(48, 3, generator=torch.Generator().manual_seed(k))) for k in range(8)]
    whole = _cache(grid, cache=decay)
    for x, d, t in batches:
        whole.train_step(x, d, t)
    first = _cache(grid, cache=decay)
    for x, d, t in batches[:4]:
        first.train_step(x, d, t)
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    buf.seek(0)
    resumed = _cache(grid, cache=decay)
    resumed.load_state_dict(torch.load(buf, weights_only=True))
    for x, d, t in batches[4:]:
        resumed.train_step(x, d, t)
    xq, dq = _batch(grid, 100, 77)
    assert torch.equal(whole.query(xq, dq), resumed.query(xq, dq))


def test_state_dict_round_trip_gives_identical_queries_and_training():
    grid = _grid()
    a = _cache(grid, seed=0)
    for i in range(4):
        x, d = _batch(grid, 64, 10 + i)
        a.train_step(x, d, torch.rand(64, 3, generator=torch.Generator().manual_seed(i)))
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = _cache(grid, seed=123)
    xq, dq = _batch(grid, 300, 99)
    assert not torch.equal(a.query(xq, dq), b.query(xq, dq))
    b.load_state_dict(torch.load(buf, weights_only=True))
    assert torch.equal(a.query(xq, dq), b.query(xq, dq))
    assert (b.n_steps, b.ema.step) == (a.n_steps, a.ema.step)
    x, d = _batch(grid, 64, 50)
    t = torch.rand(64, 3, generator=torch.Generator().manual_seed(50))
    assert a.train_step(x, d, t) == b.train_step(x, d, t)  # Adam state restored too
    assert torch.equal(a.query(xq, dq), b.query(xq, dq))


def test_query_is_chunked_consistently_and_float32():
    grid = _grid()
    small = _cache(grid, cache={**CACHE, "query_chunk": 7})
    big = _cache(grid, cache={**CACHE, "query_chunk": 1 << 16})
    x, d = _batch(grid, 50, 4)
    q = small.query(x.double(), d.double())
    assert q.dtype == torch.float32 and q.shape == (50, 3)
    torch.testing.assert_close(q, big.query(x, d))


def test_bf16_autocast_runs_the_mlp_only():
    grid = _grid()
    cache = _cache(grid, cache={**CACHE, "network": {**CACHE["network"], "bf16": True}})
    ref = _cache(grid)
    x, d = _batch(grid, 64, 5)
    assert math.isfinite(cache.train_step(x, d, torch.ones(64, 3)))
    ref.train_step(x, d, torch.ones(64, 3))
    q = cache.query(x, d)
    assert q.dtype == torch.float32
    assert cache.network.encoding.encodings[0].table.dtype == torch.float32
    torch.testing.assert_close(q, ref.query(x, d), atol=0.05, rtol=0.05)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    grid = _grid()
    cpu = _cache(grid)
    gpu = build_radiance_cache(CACHE, HASH_ONEBLOB, {}, grid, "cuda", 0)
    x, d = _batch(grid, 64, 6)
    torch.testing.assert_close(gpu.query(x, d).cpu(), cpu.query(x, d), atol=1e-5, rtol=1e-4)


def test_retain_freed_memory_is_idempotent():
    from nrc.cache.allocator import retain_freed_memory

    first = retain_freed_memory()
    assert isinstance(first, bool) and retain_freed_memory() == first
    x = torch.empty(1 << 24)  # a 64 MiB block is allocated and freed normally afterwards
    x.fill_(1.0)
    assert x.sum().item() == float(1 << 24)


# ---------------------------------------------------------------- compiled training step
@pytest.mark.slow
def test_compiled_training_step_equals_eager():
    """``compile_training``: the same losses and the same trained cache as eager, batch sizes changing (one
    dynamic graph), within float tolerance (the compiled kernels sum in another order)."""
    grid = _grid()
    eager, compiled = _cache(grid), _cache(grid, cache={**CACHE, "compile_training": True})
    assert (eager.training_backend, compiled.training_backend) == ("eager", "compiled")
    for step, n in enumerate((300, 257, 300, 123)):
        x, d = _batch(grid, n, 10 + step)
        t = torch.rand(n, 3, generator=torch.Generator().manual_seed(step))
        assert compiled.train_step(x, d, t) == pytest.approx(eager.train_step(x, d, t), rel=1e-4)
    assert compiled.training_backend == "compiled" and compiled.training_backend_reason is None
    x, d = _batch(grid, 200, 99)
    torch.testing.assert_close(compiled.query(x, d), eager.query(x, d), rtol=1e-3, atol=1e-4)
    # the NaN guard holds on the compiled path too
    before = [p.detach().clone() for p in compiled.network.parameters()]
    assert not math.isfinite(compiled.train_step(x, d, torch.full((200, 3), float("nan"))))
    assert compiled.n_skipped_steps == 1
    assert all(torch.equal(a, b) for a, b in zip(before, compiled.network.parameters()))


def test_compiled_training_step_falls_back_to_eager_with_its_reason(monkeypatch):
    def broken(fn, **kw):
        def call(*a):
            raise RuntimeError("no C++ compiler\nmore detail")
        return call
    monkeypatch.setattr(torch, "compile", broken)
    grid = _grid()
    cache, eager = _cache(grid, cache={**CACHE, "compile_training": True}), _cache(grid)
    x, d = _batch(grid, 64, 1)
    t = torch.rand(64, 3, generator=torch.Generator().manual_seed(1))
    with pytest.warns(UserWarning, match="training eagerly"):
        loss = cache.train_step(x, d, t)
    assert loss == eager.train_step(x, d, t)
    assert cache.training_backend == "eager"
    assert cache.training_backend_reason == "torch.compile of the training step failed: RuntimeError: no C++ compiler"


def test_training_graphs_bookkeeping():
    """``use_graphs`` (``renderer.cuda_graphs``) with a stand-in for ``torch.cuda.make_graphed_callables``: one capture
    per batch size, at most ``MAX_TRAINING_GRAPHS`` sizes (others eager), given the network's forward wrapped (its own
    forward untouched), the same losses and weights as without; a failed capture trains on without graphs, saying why.
    The graphs themselves: ``tests/test_cuda.py``."""
    from nrc.cache.radiance_cache import MAX_TRAINING_GRAPHS

    captured = []

    def stand_in(module, args):
        assert module.network is graphed.network and len(args) == 1 and not args[0].requires_grad
        captured.append(args[0].shape[0])
        return module

    grid = _grid()
    plain, graphed = _cache(grid), _cache(grid)
    graphed.use_graphs(stand_in)
    forward = graphed.network.forward
    sizes = (300, 257, 300, 123, 64, 65, 300)
    for step, n in enumerate(sizes):
        x, d = _batch(grid, n, 10 + step)
        t = torch.rand(n, 3, generator=torch.Generator().manual_seed(step))
        assert graphed.train_step(x, d, t) == plain.train_step(x, d, t)
    assert captured == [300, 257, 123, 64][:MAX_TRAINING_GRAPHS]
    assert graphed.graph_report == {"batch_sizes": [64, 123, 257, 300], "reason": None}
    assert graphed.network.forward == forward
    assert all(torch.equal(a, b) for a, b in zip(graphed.network.parameters(), plain.network.parameters()))

    def refuse(module, args):
        raise RuntimeError("CUDA error: operation not permitted when stream is capturing\nmore")

    broken = _cache(grid)
    broken.use_graphs(refuse)
    x, d = _batch(grid, 100, 1)
    with pytest.warns(UserWarning, match="training without CUDA graphs"):
        assert math.isfinite(broken.train_step(x, d, torch.rand(100, 3)))
    assert broken.n_steps == 1 and broken.graph_report == {
        "batch_sizes": [], "reason": "capture of a 100-record training step failed: RuntimeError: CUDA error: "
                                     "operation not permitted when stream is capturing"}
    compiled = _cache(grid, cache={**CACHE, "compile_training": True})
    compiled.use_graphs(stand_in)
    assert compiled.graph_report["reason"] == "cache.compile_training compiles the training step instead"
    bf16 = _cache(grid, cache={**CACHE, "network": {**CACHE["network"], "bf16": True}})
    bf16.use_graphs(stand_in)
    assert bf16.graph_report["reason"] == "cache.network.bf16: autocast's cast cache cannot be captured"
    assert _cache(grid).graph_report is None
