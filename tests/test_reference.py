"""Chunked, resumable reference renders (``nrc.evaluation.reference``; the app: ``nrc.reference_app``)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import compose
from nrc.errors import ConfigError, NRCError
from nrc.io import read_exr
from nrc.metrics import medium_mask
from nrc.config import config_hash, scene_hash
from nrc.render.preview import medium_alpha
from nrc.render.registry import make_renderer
from nrc.evaluation.reference import (
    REF_SEED,
    REF_SEEDS_PER_BASE,
    check_independent,
    checkpoint_path,
    read_reference,
    reference_base_seed,
    reference_seed_range,
    render_reference,
)
from nrc.scene import load_scene

TINY = [
    "renderer=pt", "scene.volume.procedural.resolution=16", "scene.camera.width=6", "scene.camera.height=4",
    "scene.integrator.seed=3",
]
CHUNK, TOTAL = 2, 8  # 4 chunks


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> tuple[np.ndarray, dict]:
    """An uninterrupted 4-chunk reference: the image returned, and the EXR's image and header."""
    out = tmp_path_factory.mktemp("full") / "ref.exr"
    image = render_reference(compose(TINY), out, CHUNK, TOTAL, progress=False)
    assert not checkpoint_path(out).exists()
    rgb, attrs = read_exr(out)
    np.testing.assert_array_equal(rgb, image)
    return image, attrs, out


def test_header_has_spp_and_config_hash(full):
    _, attrs, _ = full
    assert attrs["spp"] == TOTAL and attrs["seed"] == reference_base_seed(3) == REF_SEED + 3 * REF_SEEDS_PER_BASE
    assert attrs["config_hash"] == config_hash(compose(TINY))


def test_reference_is_the_mean_of_chunks_with_consecutive_seeds(full):
    cfg = compose(TINY + [f"scene.integrator.spp={CHUNK}"])
    chunks = []
    for i in range(TOTAL // CHUNK):
        cfg.scene.integrator.seed = reference_base_seed(3) + i
        chunks.append(make_renderer("pt", load_scene(cfg.scene), cfg).render().image.astype(np.float64))
    np.testing.assert_allclose(full[0], np.mean(chunks, axis=0), rtol=1e-6, atol=1e-7)
    assert full[0].mean() > 0
    # the header's noise floor: mean over pixels of Var(chunk) / n_chunks / (r^2 + 0.01)
    chunks = np.stack(chunks)
    n = len(chunks)
    term = chunks.var(0, ddof=1) / n / (chunks.mean(0) ** 2 + 0.01)
    assert full[1]["rel_mse_floor"] == pytest.approx(term.mean(), rel=1e-4)
    m = medium_mask(read_reference(full[2]).alpha)
    assert full[1]["rel_mse_floor_medium"] == pytest.approx(term[m].mean(), rel=1e-4)


def test_reference_stores_the_medium_alpha(full):
    ref = read_reference(full[2])
    np.testing.assert_array_equal(ref.image, full[0])
    assert ref.alpha.shape == full[0].shape[:2] and ref.alpha.dtype == np.float32
    assert 0.0 <= ref.alpha.min() and ref.alpha.max() <= 1.0
    cfg = compose(TINY)
    np.testing.assert_allclose(ref.alpha, medium_alpha(load_scene(cfg.scene)), atol=1e-6)
    m = medium_mask(ref.alpha)
    assert 0 < m.sum() <= m.size
    assert ref.attrs["scene_hash"] == scene_hash(cfg) and ref.rel_mse_floor > 0


def test_alpha_is_zero_where_the_camera_misses_the_medium():
    # the camera looks away from the cloud: no pixel sees the medium
    cfg = compose(TINY + ["scene.camera.look_at=[0,-2,400]"])
    alpha = medium_alpha(load_scene(cfg.scene))
    assert alpha.max() == 0.0 and not medium_mask(alpha).any()
    alpha = medium_alpha(load_scene(compose(TINY).scene))
    assert alpha.max() > 0.5


def test_interrupted_and_resumed_run_is_bitwise_identical(full, tmp_path):
    out = tmp_path / "ref.exr"
    assert render_reference(compose(TINY), out, CHUNK, TOTAL, progress=False, stop_after=2) is None
    with np.load(checkpoint_path(out)) as ck:
        assert int(ck["chunks_done"]) == 2
    assert not out.exists()
    image = render_reference(compose(TINY), out, CHUNK, TOTAL, progress=False)
    np.testing.assert_array_equal(image, full[0])
    np.testing.assert_array_equal(read_exr(out)[0], full[0])
    assert not checkpoint_path(out).exists()


def test_resuming_with_another_config_is_refused(tmp_path):
    out = tmp_path / "ref.exr"
    render_reference(compose(TINY), out, CHUNK, TOTAL, progress=False, stop_after=1)
    with pytest.raises(NRCError, match="different scene/renderer/transmittance config"):
        render_reference(compose(TINY + ["scene.volume.g=0.5"]), out, CHUNK, TOTAL, progress=False)
    with pytest.raises(NRCError, match="chunk_spp=2"):
        render_reference(compose(TINY), out, 4, TOTAL, progress=False)
    assert checkpoint_path(out).exists()  # left for the user to resume or delete


def test_config_hash_ignores_spp_and_seed_only():
    base = config_hash(compose(TINY))
    assert config_hash(compose(TINY + ["scene.integrator.spp=99", "scene.integrator.seed=7"])) == base
    assert config_hash(compose(TINY + ["transmittance=track_length"])) != base
    assert config_hash(compose(TINY + ["scene.integrator.max_scatter=3"])) != base


def test_scene_hash_depends_on_the_scene_only():
    base = scene_hash(compose(TINY))
    assert scene_hash(compose(TINY + ["scene.integrator.spp=99", "scene.integrator.seed=7"])) == base
    assert scene_hash(compose(TINY + ["transmittance=track_length", "renderer.slots=1024"])) == base
    assert scene_hash(compose(TINY + ["scene.volume.density_scale=0.3"])) != base


def test_bad_chunking_and_renderer_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="multiple of chunk spp"):
        render_reference(compose(TINY), tmp_path / "r.exr", 3, TOTAL, progress=False)
    with pytest.raises(ConfigError, match="renderer=pt"):
        render_reference(compose(TINY + ["renderer=preview"]), tmp_path / "r.exr", CHUNK, TOTAL, progress=False)


def test_reference_seeds_are_disjoint_from_render_seeds(full):
    """A reference asked for with seed 3 draws from the reference stream (never the seeds of a render with
    seed 3), and a comparison refuses renders whose seeds overlap the reference's."""
    _, attrs, _ = full
    used = reference_seed_range(attrs)
    assert used.start >= REF_SEED and len(used) == TOTAL // CHUNK
    check_independent(attrs, range(0, 1000))  # every ordinary render seed is independent
    with pytest.raises(ConfigError, match="not independent"):
        check_independent(attrs, [used.start + 1])
    old = {"seed": 0, "spp": 64, "chunk_spp": 16}  # a reference from before the stream: seeds 0..3
    with pytest.raises(ConfigError, match="seeds 0..3"):
        check_independent(old, [0, 1])
    assert reference_base_seed(REF_SEED + 5) == REF_SEED + 5

