"""Multiresolution hash grid: indexing against a plain-Python reference, interpolation, gradients."""

import math

import numpy as np
import pytest
import torch

from nrc.cache.encodings.hashgrid import PRIMES, HashGridEncoding


def _grid(levels=6, feats=2, log2_t=10, base=4, b=1.7, seed=0) -> HashGridEncoding:
    return HashGridEncoding(levels, feats, log2_t, base, b, generator=torch.Generator().manual_seed(seed))


def _points(n: int, seed: int = 1) -> torch.Tensor:
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed))


def _reference_corners(enc: HashGridEncoding, x: np.ndarray, level: int) -> list[tuple[int, float]]:
    """(row, weight) of the 8 corners of point ``x`` at ``level``: plain Python ints with explicit uint32
    wrap-around, the tcnn formulas written independently of the vectorised code."""
    t = enc.hashmap_size
    scale = np.float32(enc.scales[level].item())
    pos = np.float32(x) * scale + np.float32(0.5)
    cell = np.floor(pos)
    frac = pos - cell
    res = math.ceil(float(scale)) + 1
    n = res + 1
    dense = n**3 <= t
    out = []
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                v = (int(cell[0]) + i, int(cell[1]) + j, int(cell[2]) + k)
                if dense:
                    row = v[0] + v[1] * n + v[2] * n * n
                else:
                    h = 0
                    for coord, prime in zip(v, PRIMES):
                        h ^= (coord * prime) & 0xFFFFFFFF
                    row = h % t
                w = (frac[0] if i else 1 - frac[0]) * (frac[1] if j else 1 - frac[1]) * (frac[2] if k else 1 - frac[2])
                out.append((row, float(w)))
    return out


def test_output_width_and_init():
    enc = _grid(levels=5, feats=4)
    assert enc.out_dim == 20
    assert enc.table.shape == (4, sum(enc.level_sizes))
    assert enc.level_sizes == tuple((r + 1) ** 3 if d else 1024 for r, d in zip(enc.resolutions, enc.dense))
    assert enc.table.abs().max() <= 1e-4 and enc.table.abs().max() > 5e-5
    assert enc(_points(11)).shape == (11, 20)
    assert enc(_points(11)[:0]).shape == (0, 20)
    torch.testing.assert_close(_grid(seed=3).table, _grid(seed=3).table, rtol=0, atol=0)


def test_indices_and_output_match_reference():
    enc = _grid()
    assert 0 < enc.n_dense_levels < enc.n_levels  # both kinds of level are exercised
    with torch.no_grad():
        enc.table.uniform_(-1.0, 1.0, generator=torch.Generator().manual_seed(5))
    x = _points(40)
    idx, w = enc.corners(x)
    out = enc(x).detach().double().numpy()
    table = enc.table.detach().double().numpy()
    for p in range(x.shape[0]):
        for level in range(enc.n_levels):
            ref = _reference_corners(enc, x[p].numpy(), level)
            assert [r + enc.level_offsets[level] for r, _ in ref] == idx[level, :, p].tolist()
            np.testing.assert_allclose(w[level, :, p].numpy(), [wt for _, wt in ref], atol=1e-5)  # fma rounding
            for f in range(enc.n_features_per_level):
                expected = sum(wt * table[f, enc.level_offsets[level] + r] for r, wt in ref)
                assert out[p, level * enc.n_features_per_level + f] == pytest.approx(expected, abs=1e-5)


def test_hash_reproduces_uint32_wraparound_on_fine_levels():
    enc = HashGridEncoding(1, 1, 19, 3000, 1.0)  # one hashed level with coordinates up to 3000
    assert enc.dense == (False,)
    x = torch.tensor([[0.999, 0.998, 0.997], [0.5, 0.75, 0.25]])
    idx, _ = enc.corners(x)
    for p in range(2):
        ref = _reference_corners(enc, x[p].numpy(), 0)
        assert [r for r, _ in ref] == idx[0, :, p].tolist()


def test_dense_hashed_boundary():
    # T = 2^12 = 16^3. base 15: scale 14, res 15, (res+1)^3 = 4096 <= T -> dense.
    # base 16: scale 15, res 16, 17^3 = 4913 > T -> hashed. The next level (x2) is hashed in both.
    dense = HashGridEncoding(2, 2, 12, 15, 2.0)
    hashed = HashGridEncoding(2, 2, 12, 16, 2.0)
    assert dense.resolutions == (15, 30) and dense.dense == (True, False)
    assert hashed.resolutions == (16, 32) and hashed.dense == (False, False)
    # A dense level indexes every vertex of its (res+1)^3 lattice exactly once.
    g = torch.linspace(0.0, 1.0, 61)
    x = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), dim=-1).reshape(-1, 3)
    idx, _ = dense.corners(x)
    assert int(idx[0].min()) == 0 and int(idx[0].max()) == 16**3 - 1
    assert torch.unique(idx[0]).numel() == 16**3
    # The dense formula i + j n + k n^2 at a known vertex: x = 1 lands on grid coordinate 14.5.
    idx1, _ = dense.corners(torch.ones(1, 3))
    assert idx1[0, 7, 0].item() == 15 + 15 * 16 + 15 * 256


def test_linear_features_are_reproduced_exactly_on_dense_levels():
    enc = HashGridEncoding(4, 2, 15, 4, 1.5)  # resolutions 4, 6, 9, 13: all dense for T = 2^15
    assert all(enc.dense)
    a = torch.tensor([[0.3, -1.2, 2.0], [1.5, 0.25, -0.7]])  # feature f = a[f] . x + c[f]
    c = torch.tensor([0.4, -0.1])
    with torch.no_grad():
        for level, res in enumerate(enc.resolutions):
            n = res + 1
            r = torch.arange(n**3)
            vertex = torch.stack((r % n, (r // n) % n, r // (n * n)), dim=-1).double()
            pos = (vertex - 0.5) / enc.scales[level].double()  # the point that maps onto the vertex
            enc.level_table(level)[:, : n**3] = (pos @ a.double().T + c.double()).T.float()
    x = _points(500, seed=7)
    out = enc(x).detach().view(-1, enc.n_levels, 2)
    expected = x @ a.T + c
    for level in range(enc.n_levels):
        torch.testing.assert_close(out[:, level], expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_no_discontinuity_across_cell_faces(axis):
    enc = _grid(levels=6, log2_t=10)
    with torch.no_grad():
        enc.table.uniform_(-1.0, 1.0, generator=torch.Generator().manual_seed(2))
    base = _points(64, seed=4)
    eps = 1e-5
    for level in range(enc.n_levels):
        scale = enc.scales[level].item()
        face = (torch.randint(1, int(scale), (64,), generator=torch.Generator().manual_seed(level)) - 0.5) / scale
        lo, hi = base.clone(), base.clone()
        lo[:, axis], hi[:, axis] = face - eps, face + eps
        jump = (enc(hi) - enc(lo)).view(-1, enc.n_levels, 2)[:, level].abs().max().item()
        # Slope of a trilinear cell with features in [-1, 1] is at most 2 * scale per unit x.
        assert jump <= 2.0 * scale * 2 * eps + 1e-5, (level, jump)


def test_gradient_reaches_exactly_the_touched_entries():
    enc = _grid(levels=5, log2_t=9)
    x = _points(6, seed=9)
    weights = torch.randn(6, enc.out_dim, generator=torch.Generator().manual_seed(1))
    (enc(x) * weights).sum().backward()
    expected = np.zeros(tuple(enc.table.shape))
    for p in range(x.shape[0]):
        for level in range(enc.n_levels):
            for row, w in _reference_corners(enc, x[p].numpy(), level):
                for f in range(enc.n_features_per_level):
                    expected[f, enc.level_offsets[level] + row] += w * weights[p, level * enc.n_features_per_level + f].item()
    grad = enc.table.grad.double().numpy()
    np.testing.assert_allclose(grad, expected, atol=1e-6)
    assert set(zip(*np.nonzero(grad))) == set(zip(*np.nonzero(expected)))
    assert 0 < np.count_nonzero(grad) < grad.size


def test_positions_outside_are_clamped():
    enc = _grid()
    x = torch.tensor([[-0.5, 0.3, 1.7]])
    torch.testing.assert_close(enc(x), enc(torch.tensor([[0.0, 0.3, 1.0]])))
