"""Henyey–Greenstein phase function: normalisation, sampling distribution, stable forms, frames."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from nrc.transport.phase import hg_pdf, hg_sample, hg_sample_cos, orthonormal_basis


pytestmark = pytest.mark.usefixtures("single_thread")


def hg_cdf_one_minus_mu(g: float, x: np.ndarray) -> np.ndarray:
    """P(1 - mu <= x) for HG with g >= 0, in float64 (x = 1 - mu in [0, 2])."""
    if g == 0.0:
        return x / 2.0
    # P(mu' >= 1 - x) = (1 - g^2)/(2g) * (1/(1 - g) - 1/sqrt((1 - g)^2 + 2 g x)), written without cancellation
    a = 1.0 - g
    q = np.sqrt(a * a + 2.0 * g * x)
    return (1.0 - g * g) / (2.0 * g) * (q - a) / (a * q)


def hg_pdf_ref(g: float, x: np.ndarray) -> np.ndarray:
    """HG density in float64 as a function of x = 1 - mu (g >= 0)."""
    return (1.0 - g * g) / (4.0 * math.pi * ((1.0 - g) ** 2 + 2.0 * g * x) ** 1.5)


def random_dirs(n: int, gen: torch.Generator) -> torch.Tensor:
    d = torch.randn(n, 3, generator=gen)
    d = d / d.norm(dim=1, keepdim=True)
    # include the hard frames: +-z (the Duff basis singularity), the axes, and -0.0 components
    special = torch.tensor(
        [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0.0, 0.0, -0.0], [1e-8, 0, -1]], dtype=torch.float32
    )
    special[5] = torch.tensor([0.0, -0.0, -1.0])
    special = special / special.norm(dim=1, keepdim=True)
    return torch.cat((special, d))


@pytest.mark.parametrize("g", [-0.95, -0.3, 0.0, 1e-6, 0.5, 0.9, 0.99])
def test_pdf_integrates_to_one(g):
    # substitution mu = 1 - 2 w^4 (g >= 0) / mu = -1 + 2 w^4 (g < 0) concentrates nodes near the peak
    w = torch.linspace(0.0, 1.0, 400001, dtype=torch.float64)
    sign = 1.0 if g >= 0 else -1.0
    mu = sign * (1.0 - 2.0 * w**4)
    jac = 8.0 * w**3
    p = hg_pdf(g, mu.to(torch.float32)).to(torch.float64)
    total = 2.0 * math.pi * torch.trapezoid(p * jac, w)
    assert float(total) == pytest.approx(1.0, abs=2e-4)


def test_pdf_matches_textbook_formula_and_per_ray_g():
    mu = torch.linspace(-1, 1, 101)
    for g in (-0.7, 0.2, 0.8):
        ref = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * mu.double()) ** 1.5)
        torch.testing.assert_close(hg_pdf(g, mu).double(), ref, rtol=1e-5, atol=0)
    g = torch.tensor([-0.5, 0.0, 0.5])
    torch.testing.assert_close(hg_pdf(g, torch.zeros(3)), torch.stack([hg_pdf(float(x), torch.zeros(1))[0] for x in g]))


@pytest.mark.parametrize("g", [-0.9, -1e-6, 0.0, 0.3, 0.8, 0.999])
def test_sampled_cosines_follow_the_pdf(g):
    """KS test of the sampled angle against the analytic CDF, measured on the actual directions."""
    gen = torch.Generator().manual_seed(int(abs(g) * 1e6) + 3)
    n = 20000
    d = random_dirs(n, gen)
    u = torch.rand(d.shape[0], 2, generator=gen)
    new, pdf = hg_sample(g, d, u)
    assert torch.isfinite(new).all() and torch.isfinite(pdf).all()
    # unit directions
    assert float((new.norm(dim=1) - 1).abs().max()) < 2e-6
    # distance from the peak direction: x = 1 - mu for g >= 0, 1 + mu for g < 0 (HG(g, mu) = HG(-g, -mu));
    # 0.5 |a -+ b|^2 keeps full precision where the angle is tiny
    nd, dd = new.double(), d.double()
    peak = dd if g >= 0 else -dd
    x = 0.5 * ((nd - peak) ** 2).sum(dim=1)
    ga = abs(g)
    res = stats.kstest(x.numpy(), lambda v: hg_cdf_one_minus_mu(ga, np.asarray(v)))
    assert res.pvalue > 1e-3, res
    # the returned pdf is the density at the sample
    np.testing.assert_allclose(pdf.double().numpy(), hg_pdf_ref(ga, x.numpy()), rtol=2e-3)


@pytest.mark.parametrize("g", [-0.9, -0.3, 0.0, 0.4, 0.9])
def test_returned_pdf_equals_hg_pdf_at_the_sampled_cosine(g):
    gen = torch.Generator().manual_seed(11)
    u0 = torch.rand(5000, generator=gen)
    mu, sin_t, pdf = hg_sample_cos(g, u0)
    torch.testing.assert_close(pdf, hg_pdf(g, mu), rtol=2e-5, atol=0)
    torch.testing.assert_close(mu * mu + sin_t * sin_t, torch.ones_like(mu), rtol=0, atol=4e-6)


def test_g_zero_gives_s_exactly():
    gen = torch.Generator().manual_seed(5)
    u = torch.rand(10000, 2, generator=gen)
    u[:4, 0] = torch.tensor([0.0, 0.5, 1e-9, 0.99999994])
    s = 2.0 * u[:, 0] - 1.0
    mu, _, pdf = hg_sample_cos(0.0, u[:, 0])
    assert torch.equal(mu, s)
    assert torch.allclose(pdf, torch.full_like(pdf, 1 / (4 * math.pi)))
    # along +z the new direction's z component is mu itself
    z = torch.tensor([[0.0, 0.0, 1.0]]).expand(u.shape[0], 3)
    new, _ = hg_sample(0.0, z, u)
    assert torch.equal(new[:, 2], s)


def test_stable_forms_near_g_one_and_small_g():
    # 1 - mu at g = 0.9999 (from sin^2 / (1 + mu)) keeps its relative precision; exact value in float64
    g = float(torch.tensor(0.9999))  # the float32 value the implementation sees
    u0 = torch.tensor([1e-5, 0.1, 0.5, 0.9])
    mu, sin_t, _ = hg_sample_cos(g, u0)
    s = 2 * u0.double() - 1
    dd = 1 + g * s
    omm_ref = (1 - g) ** 2 * (1 - s) * (2 + g * (1 + s)) / (2 * dd * dd)
    opm_ref = 2 - omm_ref
    torch.testing.assert_close(sin_t.double() ** 2, omm_ref * opm_ref, rtol=1e-5, atol=0)
    # tiny |g|: mu is s plus an O(g) correction, no catastrophic cancellation
    for g in (1e-7, -1e-7, 1e-5):
        mu, _, _ = hg_sample_cos(g, u0)
        s = 2 * u0.double() - 1
        ref = s + 1.5 * g * (1 - s * s)  # first order in g (its mean over s is g, as it must be)
        torch.testing.assert_close(mu.double(), ref, rtol=0, atol=1e-6)


def test_per_ray_g_and_hard_values():
    gen = torch.Generator().manual_seed(2)
    n = 600
    d = random_dirs(n, gen)
    m = d.shape[0]
    g = torch.tensor([-0.999, 0.0, 0.999]).repeat(m // 3 + 1)[:m]
    u = torch.rand(m, 2, generator=gen)
    u[:6, 0] = torch.tensor([0.0, 0.0, 0.0, 1 - 2**-24, 1 - 2**-24, 1 - 2**-24])
    new, pdf = hg_sample(g, d, u)
    assert torch.isfinite(new).all() and torch.isfinite(pdf).all() and (pdf > 0).all()
    assert float((new.norm(dim=1) - 1).abs().max()) < 2e-6
    for gg in (-0.999, 0.0, 0.999):
        sel = g == gg
        new1, pdf1 = hg_sample(gg, d[sel], u[sel])
        assert torch.equal(new1, new[sel]) and torch.equal(pdf1, pdf[sel])


def test_orthonormal_basis_is_orthonormal_everywhere():
    gen = torch.Generator().manual_seed(9)
    n = random_dirs(2000, gen)
    t, b = orthonormal_basis(n)
    for v in (t, b):
        assert float((v.norm(dim=1) - 1).abs().max()) < 1e-5
    assert float((t * b).sum(1).abs().max()) < 1e-5
    assert float((t * n).sum(1).abs().max()) < 1e-5
    assert float((b * n).sum(1).abs().max()) < 1e-5
    # right-handed: t x b = n
    torch.testing.assert_close(torch.cross(t, b, dim=1), n, atol=1e-5, rtol=0)
