"""Closed-form checks of the non-parametric encodings (identity, frequency, triangle, one-blob, composite)."""

import math

import numpy as np
import pytest
import torch
from scipy.integrate import quad

from nrc.cache.encodings.composite import CompositeEncoding
from nrc.cache.encodings.frequency import FrequencyEncoding
from nrc.cache.encodings.identity import IdentityEncoding
from nrc.cache.encodings.oneblob import OneBlobEncoding
from nrc.cache.encodings.triangle import MAX_ERROR_VS_SINE, TriangleWaveEncoding


def _rand(n: int, d: int, seed: int = 0, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(n, d, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize(
    ("enc", "in_dims", "width"),
    [
        (IdentityEncoding(3), 3, 3),
        (FrequencyEncoding(3, 12), 3, 72),
        (TriangleWaveEncoding(3, 12), 3, 36),
        (OneBlobEncoding(2, 4, wrap=(False, True)), 2, 8),
        (OneBlobEncoding(3, 16, wrap=(False,) * 3), 3, 48),
    ],
)
def test_output_widths(enc, in_dims, width):
    x = _rand(7, in_dims)
    out = enc(x)
    assert enc.out_dim == width
    assert out.shape == (7, width) and out.dtype == torch.float32
    assert enc(x[:0]).shape == (0, width)


def test_identity_passes_through():
    x = _rand(5, 4, lo=-2, hi=2)
    assert torch.equal(IdentityEncoding(4)(x), x)


def test_frequency_matches_closed_form():
    n_freq = 10
    x = _rand(300, 3, lo=-1.0, hi=1.0)
    out = FrequencyEncoding(3, n_freq)(x).double()
    xd = x.double()
    for d in range(3):
        for level in range(n_freq):
            arg = 2.0**level * math.pi * xd[:, d]
            col = d * 2 * n_freq + 2 * level
            torch.testing.assert_close(out[:, col], torch.sin(arg), atol=2e-4, rtol=0)
            torch.testing.assert_close(out[:, col + 1], torch.cos(arg), atol=2e-4, rtol=0)


def test_triangle_matches_closed_form():
    n_freq = 12
    x = _rand(500, 3, seed=1)
    out = TriangleWaveEncoding(3, n_freq)(x).double().numpy()
    xd = x.double().numpy()
    for d in range(3):
        for f in range(n_freq):
            v = xd[:, d] * 2.0**f / 2.0 + 0.25 * f
            expected = 4.0 * np.abs(v - np.floor(v) - 0.5) - 1.0
            # float32 v = x 2^(f-1) + f/4 carries ~2^f * 6e-8 rounding, amplified 4x by the wave.
            np.testing.assert_allclose(out[:, d * n_freq + f], expected, atol=1e-6 + 2.0**f * 5e-7)
    assert out.min() >= -1.0 and out.max() <= 1.0


def test_triangle_error_bound_against_frequency_sine():
    """Level f of the triangle wave approximates sin(2^f pi x + (f+1) pi/2), the frequency encoding's
    sine at x + (f+1)/2^(f+1), within MAX_ERROR_VS_SINE = sqrt(1-4/pi^2) - 1 + 2 asin(2/pi)/pi ~ 0.2105
    (the largest gap between a triangle wave and the cosine with the same extrema); the bound is tight."""
    assert MAX_ERROR_VS_SINE == pytest.approx(0.210514, abs=1e-6)
    n_freq = 8
    x = torch.linspace(0.0, 1.0, 20001)[:, None]
    tri = TriangleWaveEncoding(1, n_freq)(x)
    freq = FrequencyEncoding(1, n_freq)
    for f in range(n_freq):
        shift = (f + 1) / 2.0 ** (f + 1)
        sine = freq(x + shift)[:, 2 * f]
        err = (tri[:, f] - sine).abs().max().item()
        assert err <= MAX_ERROR_VS_SINE + 1e-4
        assert err >= MAX_ERROR_VS_SINE - 2e-3
    # For f = 3 (mod 4) the phase shift is a whole period: compare with the unshifted sine directly.
    err3 = (tri[:, 3] - freq(x)[:, 6]).abs().max().item()
    assert err3 <= MAX_ERROR_VS_SINE + 1e-4


def _kernel_mass(a: float, b: float) -> float:
    """Integral of 15/16 (1-u^2)^2 over [a, b] intersected with [-1, 1] (independent of the CDF code)."""
    lo, hi = max(a, -1.0), min(b, 1.0)
    if hi <= lo:
        return 0.0
    return quad(lambda u: 15.0 / 16.0 * (1.0 - u * u) ** 2, lo, hi)[0]


@pytest.mark.parametrize("wrap", [False, True])
def test_oneblob_matches_integrated_kernel(wrap):
    k = 4
    enc = OneBlobEncoding(1, k, wrap=(wrap,))
    xs = [0.0, 0.05, 0.125, 0.3, 0.5, 0.77, 0.96, 1.0]
    out = enc(torch.tensor(xs)[:, None]).double().numpy()
    for row, x in zip(out, xs):
        for j in range(k):
            shifts = (-1.0, 0.0, 1.0) if wrap else (0.0,)
            expected = sum(_kernel_mass((j / k - x - s) * k, ((j + 1) / k - x - s) * k) for s in shifts)
            assert row[j] == pytest.approx(expected, abs=1e-6)
    assert out.min() >= 0.0


def test_oneblob_bins_sum_to_one():
    k = 8
    x = torch.linspace(0.0, 1.0, 4001)[:, None]
    plain = OneBlobEncoding(1, k, wrap=(False,))(x).sum(dim=1)
    interior = (x[:, 0] >= 1.0 / k) & (x[:, 0] <= 1.0 - 1.0 / k)
    torch.testing.assert_close(plain[interior], torch.ones(int(interior.sum())), atol=1e-6, rtol=0)
    assert (plain[~interior] < 1.0 + 1e-6).all() and plain[0] == pytest.approx(0.5, abs=1e-6)
    wrapped = OneBlobEncoding(1, k, wrap=(True,))(x).sum(dim=1)
    torch.testing.assert_close(wrapped, torch.ones_like(wrapped), atol=1e-6, rtol=0)


def test_oneblob_wraparound_is_continuous():
    enc = OneBlobEncoding(2, 4, wrap=(False, True))
    x = torch.tensor([[0.3, 0.0], [0.3, 1.0], [0.3, 1e-4], [0.3, 1.0 - 1e-4]])
    out = enc(x)
    torch.testing.assert_close(out[0], out[1], atol=1e-6, rtol=0)  # x = 0 and x = 1 agree
    assert (out[2] - out[3]).abs().max() < 1e-2  # across the seam: a small step, not a jump
    # The non-periodic column does not wrap: its values at 0 and 1 differ.
    plain = enc(torch.tensor([[0.0, 0.5], [1.0, 0.5]]))
    assert (plain[0, :4] - plain[1, :4]).abs().max() >= 0.5 - 1e-6


def test_composite_splits_columns():
    parts = [(IdentityEncoding(3), 3), (OneBlobEncoding(2, 4, wrap=(False, True)), 2), (IdentityEncoding(1), 1)]
    enc = CompositeEncoding(parts)
    x = _rand(9, 6, seed=3)
    out = enc(x)
    assert enc.in_dim == 6 and enc.out_dim == 3 + 8 + 1 and out.shape == (9, 12)
    torch.testing.assert_close(out[:, :3], x[:, :3])
    torch.testing.assert_close(out[:, 3:11], parts[1][0](x[:, 3:5]))
    torch.testing.assert_close(out[:, 11:], x[:, 5:])
