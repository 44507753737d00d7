"""nrc from Python (``nrc.run``, ``nrc.frames``, ``nrc.load_config``): the command line's images, frame by frame,
and one ``NRCError`` naming what is wrong."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest
import torch

import nrc
from conftest import REPO
from nrc.io import read_exr

TINY = ["scene.volume.procedural.resolution=16", "scene.camera.width=12", "scene.camera.height=8",
        "renderer.backend=eager", "threads=1", "denoise=none"]
NRC = ["renderer=nrc", "frames=2", "renderer.log.tensorboard=false"]


@pytest.fixture(autouse=True)
def keep_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def command_line(tmp_path, *overrides):
    proc = subprocess.run([sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path}", *overrides], cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return read_exr(tmp_path / "image.exr")[0], json.loads((tmp_path / "metrics.json").read_text())


def test_run_renders_the_command_lines_image(tmp_path):
    r = nrc.run([*TINY, "scene.integrator.seed=5"])
    image, metrics = command_line(tmp_path, *TINY, "scene.integrator.seed=5")
    np.testing.assert_array_equal(r.image, image)
    assert r.metrics["threads"] == metrics["threads"] == 1 and r.metrics["backend"] == metrics["backend"]
    assert r.denoised is None and r.out_dir is None and r.config.scene.integrator.seed == 5
    assert r.image.dtype == np.float32 and r.image.shape == (8, 12, 3)


def test_a_dict_of_overrides_is_the_list(tmp_path):
    as_dict = {"scene.volume.procedural.resolution": 16, "scene.camera.width": 12, "scene.camera.height": 8,
               "renderer.backend": "eager", "threads": 1, "denoise": "none", "scene.lights.0.direction": [0, -1, 0]}
    a = nrc.run(as_dict, out_dir=tmp_path)
    b = nrc.run([*TINY, "scene.lights.0.direction=[0,-1,0]"])
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(read_exr(tmp_path / "image.exr")[0], a.image)  # out_dir: the run's outputs
    assert (tmp_path / "metrics.json").is_file()


@pytest.mark.slow
def test_nrc_run_renders_the_command_lines_image(tmp_path):
    r = nrc.run([*TINY, *NRC])
    image, _ = command_line(tmp_path, *TINY, *NRC)
    np.testing.assert_array_equal(r.image, image)


def test_frames_yield_each_frame_and_the_last_is_the_run(tmp_path):
    frames = list(nrc.frames([*TINY, *NRC], out_dir=tmp_path / "all"))
    assert [f.index for f in frames] == [0, 1]
    assert all(f.image.shape == (8, 12, 3) and "loss" in f.stats for f in frames)
    np.testing.assert_array_equal(frames[-1].output, nrc.run([*TINY, *NRC]).image)
    # out_dir: the run's outputs once the last frame is done; a loop left early writes none
    np.testing.assert_array_equal(read_exr(tmp_path / "all" / "image.exr")[0], frames[-1].output)
    assert json.loads((tmp_path / "all" / "metrics.json").read_text())["frames_done"] == 2
    for f in nrc.frames([*TINY, *NRC], out_dir=tmp_path / "left"):
        break
    assert not (tmp_path / "left" / "image.exr").exists()


def test_leaving_the_frame_loop_stops_the_render():
    before = threading.active_count()
    seen = []
    for f in nrc.frames([*TINY, "frames=20", "renderer.log.tensorboard=false"]):
        seen.append(f.index)
        if f.index == 1:
            break
    assert seen == [0, 1]
    assert threading.active_count() == before  # the render thread has ended


def test_frames_are_the_command_lines_frames(tmp_path):
    """nrc.frames renders the command line's frames bitwise (the last one is image.exr) ..."""
    frames = list(nrc.frames([*TINY, *NRC, "scene.integrator.seed=3"]))
    image, metrics = command_line(tmp_path, *TINY, *NRC, "scene.integrator.seed=3")
    np.testing.assert_array_equal(frames[-1].output, image)
    assert [f.stats["loss"] for f in frames] == metrics["loss_per_frame"]


def test_the_frame_loop_runs_in_the_consumers_thread(monkeypatch):
    """... in the consumer's own thread, between its iterations: the settings that are per thread (grad mode, the
    intra-op threads, glibc's arena, whose fresh mappings made a helper thread's frames slower) are the caller's, as
    for ``python -m nrc``, and no thread is left behind."""
    from nrc.render.radiance_caching import NRCRenderer

    seen = []
    render_frame = NRCRenderer.render_frame

    def spy(self, frame):
        seen.append((threading.get_ident(), torch.is_grad_enabled(), torch.get_num_threads()))
        return render_frame(self, frame)

    monkeypatch.setattr(NRCRenderer, "render_frame", spy)
    before = threading.active_count()
    for f in nrc.frames([*TINY, *NRC]):
        assert threading.active_count() == before
    me = (threading.get_ident(), torch.is_grad_enabled(), 1)
    assert seen == [me, me]


@pytest.mark.parametrize("overrides, message", [
    (["scene.nope=1"], "Could not override 'scene.nope'"),
    (["scene=nope"], "Could not find 'scene/nope'"),
    (["scene.volume.albedo=2"], "scene.volume.albedo must be in [0, 1]"),
    ({"scene.volume.source": "vdb", "scene.volume.path": "missing.vdb"}, "scene.volume.path="),
    ("scene=sun", "a list of 'key=value' strings or a dict"),
    (["renderer=pt"], "nrc.frames renders renderer=nrc"),
])
def test_bad_input_is_one_nrc_error_naming_it(overrides, message):
    call = nrc.frames if message.startswith("nrc.frames") else nrc.run
    with pytest.raises(nrc.NRCError) as err:
        call(overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_import_nrc_loads_no_torch():
    proc = subprocess.run([sys.executable, "-c", "import nrc, sys; print('torch' in sys.modules, nrc.run.__name__)"],
                          capture_output=True, text=True, timeout=60)
    assert proc.stdout.split() == ["False", "run"], proc.stderr


@pytest.mark.slow
def test_the_python_example_runs_and_writes_its_plots(tmp_path):
    proc = subprocess.run([sys.executable, str(REPO / "docs" / "examples" / "from_python.py"), str(tmp_path)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "albedo.png").stat().st_size > 0 and (tmp_path / "learning.png").stat().st_size > 0
