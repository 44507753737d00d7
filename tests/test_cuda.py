"""The code on ``device=cuda`` against the CPU (skipped without CUDA; run by ``scripts/device_check.sh``).

Building blocks (encodings, the MLP, one training step) agree at tight tolerances: the same weights (same seed on
every device) and the same inputs give the same numbers up to float association. Renders agree within Monte Carlo
error (block tests over independent seeds, as against Mitsuba): the eager step and the compiled step on CUDA
against the eager step on the CPU. A short NRC run trains on CUDA and gives a finite image near the path tracer's.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import assert_images_agree, compose
from nrc.cache import build_radiance_cache
from nrc.volume.grid import DensityGrid

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

CACHE = {"network": {"n_neurons": 64, "n_hidden_layers": 3, "bf16": False},
         "optimizer": {"lr": 1e-2, "eps": 1e-15, "weight_decay": 1e-6}, "ema": {"alpha": 0.99},
         "loss": {"target_clamp": 100.0}, "query_chunk": 1 << 14}
ENCODINGS = {
    "hashgrid": {"otype": "HashGrid", "n_levels": 8, "n_features_per_level": 2, "log2_hashmap_size": 14,
                 "base_resolution": 4, "per_level_scale": 1.5},
    "triangle": {"otype": "TriangleWave", "n_frequencies": 12},
    "frequency": {"otype": "Frequency", "n_frequencies": 12},
}
ONEBLOB = {"otype": "OneBlob", "n_bins": 4}
TINY = ["scene.volume.procedural.resolution=24", "scene.camera.width=16", "scene.camera.height=8",
        "scene.integrator.max_scatter=8"]


@pytest.fixture(autouse=True)
def full_precision():
    """No TF32 in the comparisons: float32 matmuls as on the CPU."""
    old = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32 = old


def _grid(device: str) -> DensityGrid:
    return DensityGrid(torch.rand(12, 10, 8, generator=torch.Generator().manual_seed(0)), center=(0, 0, 0),
                       diagonal=2.0, density_scale=1.0, device=device)


def _points(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    x = 1.1 * (torch.rand(n, 3, generator=g) - 0.5)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    t = torch.rand(n, 3, generator=g)
    return x, d, t


def _caches(encoding: dict):
    return [build_radiance_cache(CACHE, {"position": encoding, "direction": ONEBLOB}, {}, _grid(dev), dev, 3)
            for dev in ("cpu", "cuda")]


@pytest.mark.parametrize("name", list(ENCODINGS))
def test_encoding_and_mlp_match_the_cpu(name):
    cpu, gpu = _caches(ENCODINGS[name])
    x, d, _ = _points(4096, 1)
    want = cpu.query(x, d)
    got = gpu.query(x.cuda(), d.cuda()).cpu()
    assert torch.isfinite(got).all()
    np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-4, atol=1e-5 * float(want.abs().max()) + 1e-7)


@pytest.mark.parametrize("name", ["hashgrid", "triangle"])
def test_training_steps_match_the_cpu(name):
    """Eight Adam steps from the same weights on the same batches: the losses and the trained predictions agree
    to float association (which grows a little over the steps), and the loss falls."""
    cpu, gpu = _caches(ENCODINGS[name])
    losses = {"cpu": [], "cuda": []}
    for step in range(8):
        x, d, t = _points(4096, 10 + step)
        losses["cpu"].append(cpu.train_step(x, d, t))
        losses["cuda"].append(gpu.train_step(x.cuda(), d.cuda(), t.cuda()))
    np.testing.assert_allclose(losses["cuda"], losses["cpu"], rtol=2e-3)
    assert losses["cuda"][-1] < losses["cuda"][0]
    x, d, _ = _points(2048, 99)
    np.testing.assert_allclose(gpu.query(x.cuda(), d.cuda()).cpu().numpy(), cpu.query(x, d).numpy(),
                               rtol=5e-3, atol=1e-4)


def _pt_images(overrides: list[str], device: str, backend: str, seeds: range) -> list[np.ndarray]:
    from nrc.render.registry import make_renderer
    from nrc.scene import load_scene

    images = []
    for seed in seeds:
        cfg = compose(["renderer=pt", *TINY, *overrides, f"device={device}", f"renderer.backend={backend}",
                       f"scene.integrator.seed={seed}"])
        result = make_renderer("pt", load_scene(cfg.scene, cfg.device), cfg).render()
        assert result.metrics["backend"] == backend, result.metrics["backend_reason"]
        images.append(result.image)
    return images


SCENES = {
    "sun_sky": ["scene=sun_sky", "scene.volume.albedo=0.9", "scene.integrator.spp=32"],
    "point": ["scene=point", "scene.lights.0.position=[30,70,40]", "scene.integrator.spp=32"],
}


@pytest.fixture(scope="module")
def cpu_images():
    """The CPU eager reference of each scene, seeds 100..107 (disjoint from the CUDA renders' seeds)."""
    return {name: _pt_images(o, "cpu", "eager", range(100, 108)) for name, o in SCENES.items()}


@pytest.mark.parametrize("scene,backend", [("sun_sky", "eager"), ("sun_sky", "compiled"), ("point", "eager")])
def test_path_tracer_on_cuda_matches_the_cpu(scene, backend, cpu_images):
    """One real compile (sun and sky); the point light's structure eagerly."""
    images = _pt_images(SCENES[scene], "cuda", backend, range(8))
    assert all(np.isfinite(im).all() for im in images)
    assert_images_agree(images, cpu_images[scene])


def test_short_nrc_run_on_cuda():
    """Ten NRC frames on CUDA: the cache lives and trains there, the loss is finite and falls, the image is
    finite and its mean is near the path tracer's (the early cache's bias allowed for)."""
    from nrc.render.registry import make_renderer
    from nrc.scene import load_scene

    cfg = compose(["renderer=nrc", *TINY, "scene=sun_sky", "device=cuda", "frames=10", "renderer.backend=eager",
                   "renderer.training.width=32", "renderer.training.height=32", "renderer.log.tensorboard=false"])
    renderer = make_renderer("nrc", load_scene(cfg.scene, cfg.device), cfg)
    assert next(renderer.cache.network.parameters()).is_cuda
    result = renderer.render()
    losses = [v for v in result.metrics["history"]["loss"] if v is not None]
    assert losses and np.isfinite(losses).all()
    assert np.isfinite(result.image).all() and (result.image >= 0).all()
    pt = np.mean(_pt_images(["scene=sun_sky", "scene.integrator.spp=64"], "cuda", "eager", range(2)))
    assert 0.5 * pt < result.image.mean() < 2.0 * pt


@pytest.mark.parametrize("backend", ["eager", "compiled"])
def test_cuda_graphs_give_the_same_image(backend):
    """``renderer.cuda_graphs=true``: every step call replays a captured graph of its slot bucket; the image equals
    the one without graphs (each slot's result is its own column's; the kernels are the same), and the graphs were
    used (captured, not turned off by a failed capture)."""
    over = SCENES["sun_sky"][:2] + ["scene.integrator.spp=4", "renderer.slots=4096"]
    want = _pt_images(over, "cuda", backend, range(1))[0]
    from nrc.render.registry import make_renderer
    from nrc.scene import load_scene

    cfg = compose(["renderer=pt", *TINY, *over, "device=cuda", f"renderer.backend={backend}",
                   "scene.integrator.seed=0", "renderer.cuda_graphs=true"])
    result = make_renderer("pt", load_scene(cfg.scene, cfg.device), cfg).render()
    report = result.metrics["cuda_graphs"]
    assert report["on"] and report["captures"] >= 2, report
    np.testing.assert_allclose(result.image, want, rtol=1e-5, atol=1e-6)


def test_training_graphs_match_eager_training():
    """The cache's training step through CUDA graphs (``use_graphs``, as ``renderer.cuda_graphs`` sets it): the same
    losses and trained predictions as eager training on CUDA, over batch sizes that repeat (graph replays) and
    change (new captures); the tolerances allow for the library kernels a capture may pick (float association)."""
    _, eager = _caches(ENCODINGS["hashgrid"])
    _, graphed = _caches(ENCODINGS["hashgrid"])
    graphed.use_graphs()
    for step, n in enumerate((4096, 4096, 2048, 4096, 4096)):
        x, d, t = (a.cuda() for a in _points(n, 10 + step))
        assert graphed.train_step(x, d, t) == pytest.approx(eager.train_step(x, d, t), rel=1e-4)
    assert graphed.graph_report == {"batch_sizes": [2048, 4096], "reason": None}
    x, d, _ = _points(2048, 99)
    np.testing.assert_allclose(graphed.query(x.cuda(), d.cuda()).cpu().numpy(),
                               eager.query(x.cuda(), d.cuda()).cpu().numpy(), rtol=1e-3, atol=1e-5)
