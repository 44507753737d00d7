"""The built-in procedural cloud: deterministic, bounded, cloud-shaped."""

import torch

from nrc.volume.procedural import procedural_cloud


def test_deterministic_and_seed_dependent():
    a = procedural_cloud(32, seed=1)
    b = procedural_cloud(32, seed=1)
    c = procedural_cloud(32, seed=2)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_values_shape_and_cloud_like_structure():
    d = procedural_cloud((48, 40, 32), seed=0)
    assert d.shape == (48, 40, 32) and d.dtype == torch.float32
    assert float(d.min()) >= 0.0 and float(d.max()) <= 1.0
    filled = (d > 0.01).float().mean()
    assert 0.02 < filled < 0.6  # a cloud with empty space around it, not a solid block
    # empty border (soft edges inside the box) and a flat base: nothing below the base plane
    assert float(d[0].max()) == 0.0 and float(d[-1].max()) == 0.0
    assert float(d[:, :4].max()) == 0.0
