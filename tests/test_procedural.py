"""The built-in procedural clouds: deterministic, bounded, tight boxes, and shaped as their names say."""

import math

import pytest
import torch

from conftest import compose
from nrc.errors import ConfigError
from nrc.scene import load_scene
from nrc.volume.procedural import KINDS, procedural_cloud


@pytest.mark.parametrize("kind", KINDS)
def test_deterministic_and_seed_dependent(kind):
    a = procedural_cloud(32, seed=1, kind=kind)
    b = procedural_cloud(32, seed=1, kind=kind)
    c = procedural_cloud(32, seed=2, kind=kind)
    assert torch.equal(a, b)
    assert a.shape != c.shape or not torch.equal(a, c)
    assert a.dtype == torch.float32 and float(a.min()) >= 0.0 and float(a.max()) <= 1.0


def test_blobs_is_the_original_generator():
    """`blobs` reproduces the pre-cumulus generator (values computed with it), so earlier results reproduce."""
    d = procedural_cloud((48, 40, 32), seed=3, kind="blobs")
    assert d.shape == (48, 40, 32)
    assert float(d.double().sum()) == pytest.approx(4095.2207075992164, rel=1e-6)
    assert float(d[24, 20, 16]) == pytest.approx(0.7498810291290283, abs=1e-6)
    assert float(d[30, 12, 10]) == pytest.approx(0.7735876441001892, abs=1e-6)
    assert float(d[0].max()) == 0.0 and float(d[:, :4].max()) == 0.0  # empty border, flat base


@pytest.mark.parametrize("kind", ["cumulus", "stratocumulus"])
def test_box_is_tight_around_the_density(kind):
    """One empty voxel on every face, and density in the layer next to it: the box holds the cloud only."""
    d = procedural_cloud(64, seed=0, kind=kind)
    for axis in range(3):
        for face, inner in ((0, 1), (-1, -2)):
            assert float(d.select(axis, face).max()) == 0.0
            assert float(d.select(axis, inner).max()) > 0.0


def test_cumulus_has_a_flat_base_and_a_heaped_top():
    d = procedural_cloud(64, seed=0, kind="cumulus")
    area = (d > 0.05).float().sum(dim=(0, 2))  # filled area of each horizontal layer, bottom to top
    base, widest = float(area[1:4].max()), float(area.max())
    assert base > 0.3 * widest  # cut flat at the base, not a round bottom
    top = area[int(0.8 * len(area)):]
    assert float(top.max()) < 0.35 * widest  # narrower towers on top
    assert 0.15 < float((d > 0.05).float().mean()) < 0.7


def _surface_to_volume(d: torch.Tensor) -> float:
    """Voxel faces on the boundary of ``d > 0.2`` over the surface of a sphere of the same volume (a voxelised
    sphere scores ~1.5: the faces overcount a smooth surface by the staircase)."""
    m = d > 0.2
    faces = sum(int((m.narrow(a, 1, m.shape[a] - 1) != m.narrow(a, 0, m.shape[a] - 1)).sum()) for a in range(3))
    return faces / ((36 * math.pi) ** (1 / 3) * int(m.sum()) ** (2 / 3))


@pytest.mark.parametrize("seed", [0, 1])
def test_cumulus_surface_is_billowed_not_smooth(seed):
    """Cellular erosion at two scales folds the surface: far more surface per volume than the smooth union of
    spheres of the `blobs` generator (measured 2.1-2.6 against 1.63)."""
    assert _surface_to_volume(procedural_cloud(64, seed, "cumulus")) > 1.25 * _surface_to_volume(
        procedural_cloud(64, seed, "blobs"))


def test_stratocumulus_is_a_thin_broken_deck():
    d = procedural_cloud(96, seed=0, kind="stratocumulus")
    nx, ny, nz = d.shape
    assert ny < nx / 3 and ny < nz / 3
    cover = (d.sum(dim=1) > 0.5).float().mean()  # fraction of the sky covered, seen from below
    assert 0.4 < float(cover) < 0.95


def test_another_resolution_samples_the_same_cloud():
    lo = procedural_cloud(48, seed=0, kind="cumulus")
    hi = procedural_cloud(96, seed=0, kind="cumulus")
    for a, b in zip(lo.shape, hi.shape):
        assert abs(2 * a - b) <= 4
    assert abs(float(lo.mean()) - float(hi.mean())) < 0.1 * float(hi.mean())


def test_bad_kind_names_the_key():
    with pytest.raises(ConfigError, match="scene.volume.procedural.kind"):
        load_scene(compose(["scene.volume.procedural.kind=cirrus", "scene.volume.procedural.resolution=16"]).scene)
    with pytest.raises(ValueError, match="kind"):
        procedural_cloud(16, kind="cirrus")
