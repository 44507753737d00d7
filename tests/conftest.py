"""Shared test fixtures and helpers."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
import torch._dynamo

from nrc.volume.grid import DensityGrid

REPO = Path(__file__).resolve().parent.parent
CONF_DIR = REPO / "conf"
# The lab's shared code (scripts/lab/) imports as `lab`, as it does for a script run as `python scripts/<tool>.py`
# (scripts/ first on its path): tests may put scripts/ on the path, scripts never do.
if str(REPO / "scripts") not in sys.path:
    sys.path.append(str(REPO / "scripts"))
SHARED_VDB = REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb"

# One intra-op thread per worker under pytest-xdist (two workers on two cores), else two.
torch.set_num_threads(1 if os.environ.get("PYTEST_XDIST_WORKER") else 2)
# Past Dynamo's recompile limit a compiled step would silently run eagerly: in the tests that is an error.
torch._dynamo.config.fail_on_recompile_limit_hit = True
# The suite's compiles go to a cache of its own (renderer.backend=auto reads the cache to choose: a user's warm
# cache must not change what the tests run).
os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="nrc-test-inductor-")
# Generated clouds are cached on disk (nrc/io/disk_cache.py): the suite's own, shared by its tests (and by the
# subprocesses they start), never a user's.
os.environ["NRC_CACHE_DIR"] = tempfile.mkdtemp(prefix="nrc-test-cache-")


@pytest.fixture
def fresh_machines(monkeypatch, tmp_path):
    """No compiled machines from earlier tests (a cold cache in ``tmp_path``), and none left for later ones."""
    from nrc.render.wavefront import machine as wm

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    monkeypatch.setattr(wm, "_machines", [])
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def pytest_collection_modifyitems(config, items):
    """Tests marked ``first(rank)`` (a cold compile: minutes each) move to the front of the collection, the lowest
    rank first (the rest keep their order): pytest-xdist then hands them out first, so that none of them starts last
    and runs on one worker while the other has finished (the long set's wall time; docs/testing.md)."""

    def key(item: pytest.Item) -> tuple[int, int]:
        mark = item.get_closest_marker("first")
        return (1, 0) if mark is None else (0, mark.args[0] if mark.args else 0)

    items.sort(key=key)


from nrc.config import compose  # noqa: E402  (the resolved app config, as ``python -m nrc`` sees it)


@pytest.fixture(scope="module")
def single_thread():
    """One intra-op thread for tests that run many small batched ops: as fast, and immune to a busy core."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def unit(v) -> torch.Tensor:
    """Rows of ``v`` normalised to unit length (float32)."""
    v = torch.as_tensor(v, dtype=torch.float32)
    return v / v.norm(dim=-1, keepdim=True)


def constant_grid():
    """A small constant-density grid (sigma_t = 0.8 everywhere in its box)."""
    return DensityGrid(torch.ones(6, 5, 4), center=(0.2, -0.1, 0.3), diagonal=3.0, density_scale=0.8)


@pytest.fixture
def shared_vdb() -> Path:
    if not SHARED_VDB.is_file():
        pytest.skip(f"shared Disney cloud not found at {SHARED_VDB}")
    return SHARED_VDB


def hard_rays(grid):
    """Rays from inside, grazing faces and edges, along axes, and missing the box."""
    lo, hi, c, ext = grid.box.lo, grid.box.hi, grid.box.center, grid.box.extent
    o = [
        c, c + 0.3 * ext, lo + 1e-6,  # inside, at a corner
        torch.stack([lo[0] - 1, c[1], hi[2]]),  # grazing the +z face
        torch.stack([lo[0] - 1, lo[1], lo[2]]),  # grazing an edge
        torch.stack([c[0], hi[1] + 1, c[2]]),  # down the y axis
        torch.stack([lo[0] - 1, hi[1] + 1, c[2]]),  # misses
        c + 5 * ext,  # outside, pointing away
    ]
    d = [
        [0.3, 0.2, 0.1], [0.0, 0.0, -1.0], [1.0, 1.0, 1.0],
        [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 1.0],
    ]
    return torch.stack(o), unit(torch.tensor(d))


def spike_grid():
    """A single dense voxel in an empty 7^3 grid (sigma_t 50 at its centre)."""
    D = torch.zeros(7, 7, 7)
    D[3, 3, 3] = 1.0
    return DensityGrid(D, center=(0, 0, 0), diagonal=2.0, density_scale=50.0)


def block_stats(images: list[np.ndarray], block: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error of block-averaged images over independent renders ``(H, W, 3)`` each."""
    stack = np.stack(images)  # (R, H, W, 3)
    r, h, w, c = stack.shape
    blocks = stack[:, : h // block * block, : w // block * block].reshape(r, h // block, block, w // block, block, c)
    per_render = blocks.mean(axis=(2, 4))
    return per_render.mean(0), per_render.std(0, ddof=1) / np.sqrt(r)


def assert_images_agree(a: list[np.ndarray], b: list[np.ndarray], block: int = 4) -> None:
    """Two renderers agree within Monte Carlo error over independent renders (seeds) of each.

    Block means within 4.5 standard errors (for 16x8 images: 2 x 4 blocks x 3 channels = 24 comparisons),
    image means within 4 (standard errors from the spread over renders).
    """
    m_a, se_a = block_stats(a, block)
    m_b, se_b = block_stats(b, block)
    z = (m_a - m_b) / np.maximum(np.sqrt(se_a**2 + se_b**2), 1e-6 * np.abs(m_b).max())
    assert np.abs(z).max() < 4.5, f"max |z| = {np.abs(z).max():.2f}"
    mean_a, mean_b = (np.array([im.mean() for im in ims]) for ims in (a, b))
    se_mean = np.sqrt((mean_a.var(ddof=1) + mean_b.var(ddof=1)) / len(a))
    assert abs(mean_a.mean() - mean_b.mean()) < 4 * se_mean
    assert mean_b.mean() > 0


LANTERN_POSITION = (5.0, -20.0, 10.0)  # conf/scene/lantern.yaml


def hollow_lantern(tmp_path: Path, radius: float = 12.0) -> list[str]:
    """Overrides of the lantern preset on the 24^3-lattice cumulus with the density zeroed within ``radius`` of
    the light (a pocket of clear air inside the cloud, ~3 units across after interpolation): next-event
    estimation's ``1/r^2`` then has finite variance, so a block test can decide (with density at the light its
    variance is infinite and image means converge too slowly for a test)."""
    from nrc.config import compose as compose_cfg
    from nrc.scene import load_scene
    from nrc.volume.procedural import clear_pocket

    cfg = compose_cfg(["scene=lantern", "scene.volume.procedural.resolution=24"])
    path = tmp_path / "hollow.npz"
    np.savez(path, density=clear_pocket(load_scene(cfg.scene).grid, LANTERN_POSITION, radius).numpy())
    return ["scene=lantern", "scene.volume.source=npz", f"scene.volume.path={path}"]


def load_script(name: str):
    """``scripts/<name>.py`` as a module (the command lines live there, not in the package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"script_{name}", REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # what a dataclass in the script looks itself up by
    spec.loader.exec_module(module)
    return module
