"""Error metrics on hand-made images with known bias and variance."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nrc.metrics import (
    flicker,
    error_report,
    mean_relative_bias,
    medium_mask,
    mse,
    rel_mse,
    relative_variance,
    signed_relative_bias,
    thesis_relative_bias,
    thesis_relative_variance,
)

EPS = 0.01


def noisy_renders(r: float, b: float, sigma: float, k: int = 4000, shape=(4, 5), seed: int = 0) -> np.ndarray:
    """K renders of a constant image ``r``: ``r (1 + b) + N(0, sigma^2)`` per pixel and channel."""
    rng = np.random.default_rng(seed)
    return r * (1 + b) + sigma * rng.standard_normal((k, *shape, 3))


def test_rel_mse_and_mse_hand_computed_2x2():
    ref = np.array([[[1.0] * 3, [0.0] * 3], [[2.0] * 3, [0.5] * 3]])
    x = np.array([[[1.5] * 3, [0.1] * 3], [[2.0] * 3, [0.0] * 3]])
    # per pixel: 0.25/1.01, 0.01/0.01, 0/4.01, 0.25/0.26
    expected = (0.25 / 1.01 + 1.0 + 0.0 + 0.25 / 0.26) / 4
    assert rel_mse(x, ref) == pytest.approx(expected, rel=1e-12)
    assert mse(x, ref) == pytest.approx((0.25 + 0.01 + 0 + 0.25) / 4, rel=1e-12)
    assert isinstance(rel_mse(torch.tensor(x), torch.tensor(ref)), float)


def test_mean_relative_bias_and_relative_variance_recover_known_values():
    r, b, sigma, k = 0.5, 0.1, 0.2, 4000
    xs = noisy_renders(r, b, sigma, k)
    # Bias: the K-mean carries noise sigma / sqrt(K) = 0.0032 against a bias b r = 0.05 (>15 sigma).
    assert mean_relative_bias(xs, np.full((4, 5, 3), r)) == pytest.approx(b * r / (r + EPS), rel=0.02)
    assert signed_relative_bias(xs, np.full((4, 5, 3), r)) == pytest.approx(b * r / (r + EPS), rel=0.02)
    # Variance: 60 pixel-channels x 4000 renders; the relative standard error of the mean is sqrt(2 / K / 60) = 0.3 %.
    assert relative_variance(xs, np.full((4, 5, 3), r)) == pytest.approx(sigma**2 / (r**2 + EPS), rel=0.02)


def test_signed_bias_sign_and_unbiased_floor():
    ref = np.full((4, 5, 3), 0.5)
    assert signed_relative_bias(noisy_renders(0.5, -0.2, 0.05, k=200), ref) < 0
    assert signed_relative_bias(noisy_renders(0.5, 0.2, 0.05, k=200), ref) > 0
    # Unbiased renders: only the noise floor sqrt(2/pi) sigma / sqrt(K) / (r + eps) remains.
    floor = np.sqrt(2 / np.pi) * 0.05 / np.sqrt(200) / (0.5 + EPS)
    assert mean_relative_bias(noisy_renders(0.5, 0.0, 0.05, k=200), ref) == pytest.approx(floor, rel=0.3)


def test_cancelling_errors_fool_the_thesis_bias_only():
    ref = np.full((2, 4, 3), 1.0)
    x = ref.copy()
    x[:, :2] += 0.3
    x[:, 2:] -= 0.3
    assert thesis_relative_bias(x, ref) == pytest.approx(0.0, abs=1e-12)
    assert mean_relative_bias(x[None], ref) == pytest.approx(0.3 / (1 + EPS), rel=1e-12)


def test_thesis_variance_measures_image_content_not_noise():
    ref = np.zeros((2, 2, 3))
    ref[0] = 1.0  # mean 0.5, spatial variance 0.25
    xs = np.stack([ref, ref])  # noise-free renders
    assert thesis_relative_variance(ref, ref) == pytest.approx(0.25 / 0.5)
    assert relative_variance(xs, ref) == 0.0


def test_masks_select_pixels():
    ref = np.ones((3, 3, 3))
    x = ref.copy()
    x[1, 1] = 3.0  # the only wrong pixel
    alpha = np.zeros((3, 3))
    alpha[1, 1] = 0.7
    m = medium_mask(alpha)
    assert m.dtype == bool and m.sum() == 1 and m[1, 1]
    assert mse(x, ref, mask=m) == pytest.approx(4.0)
    assert mse(x, ref) == pytest.approx(4.0 / 9)
    assert mse(x, ref, mask=~m) == 0.0
    assert mean_relative_bias(x[None], ref, mask=m) == pytest.approx(2.0 / (1 + EPS))
    assert thesis_relative_bias(x, ref, mask=m) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="no pixels"):
        mse(x, ref, mask=np.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="does not match"):
        mse(x, ref, mask=np.ones((2, 3), bool))


def test_variance_needs_two_renders_and_shapes_are_checked():
    ref = np.ones((2, 2, 3))
    with pytest.raises(ValueError, match="K >= 2"):
        relative_variance(ref[None], ref)
    with pytest.raises(ValueError, match="shape"):
        mse(np.ones((2, 3, 3)), ref)


def test_error_report_is_json_and_consistent():
    r = 0.5
    ref = np.full((4, 5, 3), r)
    xs = noisy_renders(r, 0.1, 0.2, k=8)
    mask = np.zeros((4, 5), bool)
    mask[:2] = True
    rep = json.loads(json.dumps(error_report(torch.tensor(xs), ref, mask)))
    assert rep["renders"] == 8 and set(rep) == {"renders", "all", "medium"}
    assert rep["all"]["relative_variance"] == pytest.approx(relative_variance(xs, ref))
    assert rep["medium"]["mean_relative_bias"] == pytest.approx(mean_relative_bias(xs, ref, mask))
    assert rep["all"]["rel_mse"] == pytest.approx(np.mean([rel_mse(x, ref) for x in xs]))
    single = error_report(xs[0], ref)
    assert single["renders"] == 1 and single["all"]["relative_variance"] is None and single["medium"] is None


def test_normalised_rel_mse_does_not_forgive_a_dark_image():
    """A uniformly 35 % too dark image of a dim scene (reference 0.1): plain relMSE is tiny because of its
    +0.01, the normalised one (reference mean luminance 1) is not."""
    from nrc.metrics import mean_ratio, normalised_rel_mse, reference_scale

    ref = np.full((4, 6, 3), 0.1)
    dark = 0.65 * ref
    assert rel_mse(dark, ref) == pytest.approx(0.035**2 / (0.01 + 0.01))
    assert reference_scale(ref) == pytest.approx(0.1)
    assert normalised_rel_mse(dark, ref) == pytest.approx(0.35**2 / (1.0 + 0.01))
    assert mean_ratio(dark, ref) == pytest.approx(0.65)
    mask = np.zeros((4, 6), bool)
    mask[:2] = True
    ref2 = ref.copy()
    ref2[2:] = 0.0  # sky pixels: the scale comes from the medium pixels only
    assert reference_scale(ref2, mask) == pytest.approx(0.1)
    assert normalised_rel_mse(0.65 * ref2, ref2, mask, mask) == pytest.approx(0.35**2 / 1.01)


def test_hdr_flip_on_known_pairs():
    pytest.importorskip("flip_evaluator")
    from nrc.metrics import hdr_flip

    rng = np.random.default_rng(1)
    ref = rng.uniform(0.2, 1.0, size=(32, 32, 3)).astype(np.float32)
    assert hdr_flip(ref, ref) == pytest.approx(0.0, abs=1e-6)
    small = hdr_flip(ref * 1.05, ref)
    large = hdr_flip(ref * 0.5, ref)
    assert 0.0 < small < large < 1.0


def test_flicker_on_a_hand_made_sequence():
    ref = np.full((2, 2, 3), 2.0)
    still = np.stack([np.full((2, 2, 3), 1.5)] * 4)
    assert flicker(still, ref) == 0.0
    seq = np.stack([np.full((2, 2, 3), v) for v in (1.0, 3.0, 2.0)])  # steps of 2 and 1: mean 1.5, over 2
    assert flicker(seq, ref) == pytest.approx(0.75)
    seq[:, 0, 0] = 100.0  # a pixel outside the mask changes nothing when masked out
    seq[1, 0, 0] = 0.0
    mask = np.ones((2, 2), dtype=bool)
    mask[0, 0] = False
    assert flicker(seq, ref, mask) == pytest.approx(0.75)
    assert flicker(seq, ref) > 10
    rng = np.random.default_rng(0)  # independent noise of standard deviation s: 2 s / sqrt(pi) over the mean
    noisy = 1.0 + 0.1 * rng.standard_normal((64, 32, 32, 3))
    assert flicker(noisy, np.ones((32, 32, 3))) == pytest.approx(0.2 / np.sqrt(np.pi), rel=0.02)
    with pytest.raises(ValueError, match="K >= 2"):
        flicker(seq[:1], ref)
