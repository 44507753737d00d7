"""The Hydra app end to end: outputs on success, one clear message (no traceback) on bad input."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from nrc.io import read_exr

TINY = ["scene.volume.procedural.resolution=16", "scene.camera.width=12", "scene.camera.height=8"]


def run_app(tmp_path, *overrides):
    cmd = [sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path}", *TINY, *overrides]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)


def test_app_writes_exr_png_and_metrics(tmp_path):
    proc = run_app(tmp_path, "renderer=preview")
    assert proc.returncode == 0, proc.stderr
    img, _ = read_exr(tmp_path / "image.exr")
    assert img.shape == (8, 12, 3) and np.isfinite(img).all()
    assert (tmp_path / "preview.png").stat().st_size > 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["renderer"] == "preview" and metrics["time_total_s"] > 0
    assert (tmp_path / ".hydra" / "config.yaml").is_file()  # the scene contract of this run


@pytest.mark.parametrize(
    "override, message",
    [
        ("scene.volume.g=1.5", "scene.volume.g must be in (-1, 1)"),
        ("device=cuda", "CUDA is not available"),
        ("scene.lights.0.type=spot", "scene.lights[0].type"),
    ],
)
def test_app_reports_bad_input_in_one_line(tmp_path, override, message):
    if override == "device=cuda":
        torch = pytest.importorskip("torch")
        if torch.cuda.is_available():
            pytest.skip("CUDA is available here")
    proc = run_app(tmp_path, "renderer=preview", override)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_default_scene_preview_shows_the_cloud(tmp_path):
    """The default scene's preview (auto exposure, ACES) at a quarter of the default size: the cloud covers a
    quarter of the frame or more, the mean display luminance is mid-grey, almost nothing clips."""
    from PIL import Image

    proc = subprocess.run([sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path}", "renderer=pt",
                           "scene.camera.width=80", "scene.camera.height=45", "scene.integrator.spp=8"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    png = np.asarray(Image.open(tmp_path / "preview.png")).astype(np.float32) / 255.0
    lum = png @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    assert 0.2 <= lum.mean() <= 0.6
    assert (png >= 1.0).any(-1).mean() <= 0.01
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["preview"]["tonemap"] == "aces" and metrics["preview"]["exposure"] > 0
    from nrc.config import compose
    from nrc.render.preview import medium_alpha
    from nrc.scene import load_scene

    alpha = medium_alpha(load_scene(compose(["scene.camera.width=80", "scene.camera.height=45"]).scene))
    assert (alpha > 0.1).mean() >= 0.25


def test_app_rejects_a_bad_exposure_before_rendering(tmp_path):
    proc = run_app(tmp_path, "renderer=preview", "exposure=-1")
    assert proc.returncode == 2 and "exposure must be 'auto' or a positive finite number" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "image.exr").exists()


NRC_TINY = ["renderer=nrc", "frames=3", "renderer.training.width=8", "renderer.training.height=8",
            "cache.network.n_neurons=16", "cache.network.n_hidden_layers=1", "encoding.position.n_levels=2",
            "encoding.position.log2_hashmap_size=10", "renderer.log.image_every=1"]


def test_app_runs_the_nrc_frame_loop(tmp_path):
    """`python -m nrc renderer=nrc frames=N` writes the image, the per-frame metrics, TensorBoard logs and a
    checkpoint that a second run resumes from."""
    first = tmp_path / "first"
    proc = run_app(first, *NRC_TINY)
    assert proc.returncode == 0, proc.stderr
    img, _ = read_exr(first / "image.exr")
    assert img.shape == (8, 12, 3) and np.isfinite(img).all()
    metrics = json.loads((first / "metrics.json").read_text())
    assert metrics["renderer"] == "nrc" and len(metrics["loss_per_frame"]) == 3
    assert len(metrics["time_trace_s"]) == len(metrics["time_infer_s"]) == len(metrics["time_train_s"]) == 3
    assert list((first / "tensorboard").glob("events.out.tfevents.*"))
    resumed = tmp_path / "resumed"
    proc = run_app(resumed, *NRC_TINY, "frames=5", f"renderer.resume={first / 'checkpoint.pt'}")
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((resumed / "metrics.json").read_text())
    assert metrics["first_frame"] == 3 and len(metrics["loss_per_frame"]) == 5


@pytest.mark.slow
def test_multirun_sweeps_with_the_joblib_launcher(tmp_path):
    """`-m` sweeps run each job into its own directory, in parallel processes with hydra/launcher=joblib."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    cmd = [sys.executable, "-m", "nrc", "-m", f"hydra.sweep.dir={tmp_path}", "hydra/launcher=joblib",
           "hydra.launcher.n_jobs=2", *TINY, *NRC_TINY, "frames=1", "batch_filter=none,stripes",
           "renderer.backend=eager"]  # the launcher, not the compile (the sweep would build the step first: test_sweeps.py)
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    for job in ("0", "1"):
        metrics = json.loads((tmp_path / job / "metrics.json").read_text())
        assert metrics["renderer"] == "nrc" and len(metrics["loss_per_frame"]) == 1


@pytest.mark.slow
def test_a_wheel_install_runs_outside_the_checkout(tmp_path):
    """`pip install` of the built wheel into a fresh venv runs `python -m nrc` from a directory with no conf/
    beside it. The venv reuses this interpreter's packages (torch, hydra, ...) through a .pth path entry, which
    adds the directory without running its .pth files, so an editable install of nrc there stays invisible."""
    import sysconfig
    import venv

    wheel_dir = tmp_path / "dist"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation",
                            "-w", str(wheel_dir), "-q"], capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr
    (wheel,) = wheel_dir.glob("nrc-*.whl")
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (Path(site) / "host_packages.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    inst = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "-q", str(wheel)], capture_output=True,
                          text=True, timeout=600)
    assert inst.returncode == 0, inst.stderr
    work = tmp_path / "elsewhere"
    work.mkdir()
    proc = subprocess.run([str(py), "-m", "nrc", "renderer=preview", "hydra.run.dir=out", *TINY], cwd=work,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert (work / "out" / "image.exr").is_file()
    where = subprocess.run([str(py), "-c", "import nrc.config as c; print(c.CONF_DIR)"], cwd=work,
                           capture_output=True, text=True, timeout=60).stdout.strip()
    assert str(env_dir) in where  # the packaged configs, not the checkout's
    # nothing locates the checkout: the default reference folder is under the working directory (not beside
    # site-packages), and the code version names no git revision
    env = {k: v for k, v in os.environ.items() if k != "NRC_REFERENCE_DIR"}
    probe = ("from nrc.config import code_version, compose; from nrc.evaluation.reference import "
             "default_reference_path; print(default_reference_path(compose([]), 8)); print(code_version())")
    ref, version = subprocess.run([str(py), "-c", probe], cwd=work, env=env, capture_output=True, text=True,
                                  timeout=120, check=True).stdout.strip().splitlines()[-2:]
    assert Path(ref).parent == work / "data" / "references" and "(" not in version


@pytest.mark.slow
def test_multirun_with_the_submitit_launcher(tmp_path):
    """`hydra/launcher=submitit_local` (the `cluster` extra) runs the real submitit executor: two jobs."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    cmd = [sys.executable, "-m", "nrc", "-m", "hydra/launcher=submitit_local", f"hydra.sweep.dir={tmp_path}",
           "hydra.launcher.timeout_min=5", "renderer=preview", *TINY, "scene.camera.width=8,12"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    for job, width in (("0", 8), ("1", 12)):
        img, _ = read_exr(tmp_path / job / "image.exr")
        assert img.shape == (8, width, 3)
