"""Long runs that survive faults and bad input: checkpoints, interrupts, NaN/Inf, output and config errors."""

import json
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from conftest import REPO, compose
from nrc.errors import ConfigError, NRCError
from nrc.io import read_exr
from nrc.render.registry import make_renderer
from nrc.render.radiance_caching.checkpoint import CheckpointError, config_differences, load_checkpoint
from nrc.scene import load_scene

TINY = ["renderer=nrc", "scene.volume.procedural.resolution=16", "scene.camera.width=12", "scene.camera.height=8",
        "renderer.training.width=8", "renderer.training.height=8", "cache.network.n_neurons=16",
        "cache.network.n_hidden_layers=1", "encoding.position.n_levels=2", "encoding.position.log2_hashmap_size=10",
        "renderer.log.tensorboard=false"]


def nrc(out_dir, *overrides, frames=3):
    cfg = compose([*TINY, f"frames={frames}", *overrides])
    r = make_renderer("nrc", load_scene(cfg.scene), cfg)
    if out_dir is not None:
        r.attach_output(out_dir)
    return r


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    out = tmp_path_factory.mktemp("first")
    nrc(out).render()
    return out / "checkpoint.pt"


def corrupt(kind, good, path):
    data = good.read_bytes()
    if kind == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif kind == "text":
        path.write_text("this is not a checkpoint\n")
    elif kind == "flipped":
        mid = len(data) // 2
        path.write_bytes(data[:mid] + bytes(b ^ 0xFF for b in data[mid:mid + 50]) + data[mid + 50:])
    elif kind == "pickle":  # a plain torch.save, as nrc wrote before the checkpoint format
        torch.save({"frame": 3}, path)
    elif kind == "empty":
        path.write_bytes(b"")
    return path


@pytest.mark.parametrize("kind, message", [
    ("truncated", "corrupted (checksum mismatch"), ("flipped", "corrupted (checksum mismatch"),
    ("text", "is not an nrc checkpoint"), ("pickle", "is not an nrc checkpoint"), ("empty", "is not an nrc checkpoint"),
    ("missing", "no such checkpoint"),
])
def test_a_malformed_checkpoint_is_one_message_naming_the_file(checkpoint, tmp_path, kind, message):
    path = tmp_path / "bad.pt" if kind == "missing" else corrupt(kind, checkpoint, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match=re.escape(message)) as err:
        nrc(None, f"renderer.resume={path}", frames=5).render()
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_the_app_reports_a_corrupted_checkpoint_in_one_line(checkpoint, tmp_path):
    bad = corrupt("flipped", checkpoint, tmp_path / "bad.pt")
    proc = subprocess.run([sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path / 'run'}", *TINY, "frames=5",
                           f"renderer.resume={bad}"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "checksum mismatch" in proc.stderr and str(bad) in proc.stderr


@pytest.mark.parametrize("override, key", [
    ("scene.camera.width=16", "scene.camera.width"), ("scene.integrator.seed=5", "scene.integrator.seed"),
    ("encoding.position.n_levels=3", "encoding.position.n_levels"), ("scene=sun_front", "scene.lights"),
    ("renderer.accumulate=true", "renderer.accumulate"),
])
def test_resume_refuses_another_configuration_naming_the_keys(checkpoint, override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        nrc(None, f"renderer.resume={checkpoint}", override, frames=5).render()


def test_resume_accepts_the_keys_that_may_change(checkpoint, tmp_path):
    r = nrc(tmp_path, f"renderer.resume={checkpoint}", "renderer.checkpoint_every=2", "renderer.log.image_every=1",
            "exposure=2", frames=4)
    metrics = r.render().metrics
    assert metrics["first_frame"] == 3 and metrics["frames_done"] == 4
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert config_differences(state["config"], compose([*TINY, "frames=9"])) == []


def test_a_diverging_cache_stops_the_run_and_nothing_is_hidden(tmp_path):
    """NaN injected into the cache network: the predictions are counted, no step reaches Adam, and after 8
    non-finite steps in a row the run stops with a message (the last good checkpoint stays)."""
    r = nrc(tmp_path, "renderer.checkpoint_every=1", "batch_filter=stripes", frames=20)
    net = r.cache.network
    forward = net.forward
    calls = {"n": 0}

    def poisoned(x):
        calls["n"] += 1
        out = forward(x)
        return out * float("nan") if calls["n"] > 6 else out

    net.forward = poisoned
    before = [p.detach().clone() for p in net.parameters()]
    with pytest.raises(NRCError, match="NaN/Inf for 8 steps in a row") as err:
        r.render()
    assert "last good checkpoint" in str(err.value) or "no checkpoint" in str(err.value)
    assert r.cache.n_skipped_steps >= 8
    after = list(net.parameters())
    assert all(torch.isfinite(p).all() for p in after)  # NaN never reached the weights
    assert any(not torch.equal(a, b) for a, b in zip(before, after))  # the good steps did train
    if r.checkpoint_path is not None:
        assert load_checkpoint(r.checkpoint_path)["frame"] == r.checkpoint_frame


def run_app(run_dir, *overrides, timeout=300):
    return subprocess.run([sys.executable, "-m", "nrc", f"hydra.run.dir={run_dir}", *overrides], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


SMALL_PT = ["renderer=pt", "scene.volume.procedural.resolution=16", "scene.camera.width=12", "scene.camera.height=8"]


@pytest.mark.parametrize("overrides, message, code", [
    (["scene.lights=foo"], "scene.lights must be a list", 2),
    ([*TINY, "renderer.accumulate=true", "renderer.animate.mode=orbit"], "cannot be used with renderer.animate", 2),
    ([*TINY, "renderer.checkpoint_every=-3"], "renderer.checkpoint_every must be auto or an integer", 2),
    (["exposure=nan"], "exposure must be 'auto' or a positive finite number", 2),
    (["tonemap=filmic"], "tonemap must be one of", 2),
    (["frames=5"], "frames=5 is ignored by renderer=pt", 0),
    (["scene.volume.path=cloud.vdb"], "scene.volume.path=", 0),
    (["scene=base"], "scene.lights is empty", 0),
])
def test_bad_or_ignored_input_is_one_line(tmp_path, overrides, message, code):
    proc = run_app(tmp_path / "run", *SMALL_PT, *overrides)
    assert proc.returncode == code, proc.stderr
    out = proc.stdout + proc.stderr  # warnings go through the log (Hydra prints it on stdout), errors to stderr
    assert message in out and "Traceback" not in out


def test_an_output_name_in_the_way_is_one_line(tmp_path):
    (tmp_path / "run" / "image.exr").mkdir(parents=True)
    proc = run_app(tmp_path / "run", *SMALL_PT)
    assert proc.returncode == 2 and "cannot write" in proc.stderr and "image.exr" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_image_exr_carries_alpha_and_metadata(tmp_path):
    import OpenEXR

    proc = run_app(tmp_path, *SMALL_PT)
    assert proc.returncode == 0, proc.stderr
    with OpenEXR.File(str(tmp_path / "image.exr"), separate_channels=True) as f:
        names, header = set(f.channels()), dict(f.header())
        alpha = f.channels()["A"].pixels.copy()
    assert {"R", "G", "B", "A"} <= names
    assert 0.0 <= alpha.min() and alpha.max() <= 1.0 and alpha.max() > 0.5 and alpha.min() < 0.1
    for key in ("renderer", "spp", "seed", "config_hash", "code"):
        assert key in header
    img, _ = read_exr(tmp_path / "image.exr")  # readers take RGBA
    assert img.shape == (8, 12, 3)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["nonfinite_pixels"] == 0


@pytest.mark.slow
def test_sigterm_checkpoints_and_the_resumed_run_equals_an_uninterrupted_one(tmp_path):
    """SIGTERM mid-run: exit 143, a checkpoint and the outputs of the frames done, the resume command printed;
    resuming to the end gives the image of a run that was never interrupted (24 frames: the signal comes after
    the first checkpoint, within a frame or two)."""
    frames = 24
    args = [*TINY, f"frames={frames}", "renderer.checkpoint_every=1"]
    cmd = [sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path / 'cut'}", *args]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ckpt = tmp_path / "cut" / "checkpoint.pt"
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert "resume with:" in err and "renderer.resume=" in err and "Traceback" not in err
    cut = json.loads((tmp_path / "cut" / "metrics.json").read_text())
    assert cut["interrupted"] == "SIGTERM" and 1 <= cut["frames_done"] < frames
    assert load_checkpoint(ckpt)["frame"] == cut["frames_done"]
    resumed = run_app(tmp_path / "resumed", *args, f"renderer.resume={ckpt}")
    assert resumed.returncode == 0, resumed.stderr
    whole = run_app(tmp_path / "whole", *args)
    assert whole.returncode == 0, whole.stderr
    a, _ = read_exr(tmp_path / "resumed" / "image.exr")
    b, _ = read_exr(tmp_path / "whole" / "image.exr")
    np.testing.assert_array_equal(a, b)


@pytest.mark.slow
@pytest.mark.parametrize("renderer", ["pt", "nrc"])
def test_ctrl_c_during_a_compile_stops_within_seconds(tmp_path, renderer):
    """A cold compile says what it does; Ctrl-C (SIGINT to the process group, as a terminal sends it) during it
    stops the run within seconds with one line, for the path tracer and for NRC before its first frame."""
    import os
    import threading

    env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "inductor"))
    tiny = TINY if renderer == "nrc" else ["scene.volume.procedural.resolution=16", "scene.camera.width=12",
                                            "scene.camera.height=8", "scene.integrator.spp=1"]
    cmd = [sys.executable, "-m", "nrc", f"hydra.run.dir={tmp_path / 'run'}", f"renderer={renderer}",
           "renderer.backend=compiled", *(a for a in tiny if not a.startswith("renderer=")), "frames=3"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True,  # Hydra logs to stdout, errors go to stderr: both read
                            # as from a terminal: CI and xdist workers may run with SIGINT ignored, which a child
                            # inherits (and then Python installs no KeyboardInterrupt handler)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines: list[str] = []
    seen = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
            if "compiling the transport step" in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    assert seen.wait(120), "".join(lines)[-2000:]
    time.sleep(2)  # inside the compile (a cold one takes a minute or more)
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=120)
    reader.join(10)
    err = "".join(lines)
    # 130 (the app's exit), or SIGINT itself where a signal lands in the interpreter's shutdown after the app's exit
    # (its handlers are then back to the default): a shell reports both as 130. Seen once, in a CI run on a slow host
    # (docs/measurements/ci.md); the one line below is required either way
    assert proc.returncode in (130, -signal.SIGINT), err[-2000:]
    assert "interrupted by SIGINT" in err and "Traceback" not in err
    assert "compiled the transport step in" not in err  # it stopped the compile instead of waiting for it
    assert not (tmp_path / "run" / "image.exr").exists()


def test_bench_nrc_frame_needs_more_frames_than_it_skips():
    """``--frames`` not above ``--skip`` would leave no frame to take the median of: one usage line, exit 2."""
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "bench_nrc_frame.py"), "--frames", "2", "--skip", "2"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "must exceed --skip" in r.stderr and "Traceback" not in r.stderr


def test_a_ctrl_c_inside_an_ahead_of_time_build_is_a_stop():
    """Ctrl-C inside the AOT build stops it however torch's tracing treats the ``KeyboardInterrupt`` (it can turn it
    into another exception or swallow it): raised again until the block is left, and raised on leaving."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are set in the main thread only")
    ignored = signal.getsignal(signal.SIGINT)
    if not callable(ignored):  # CI's run and xdist workers may ignore SIGINT: Python's own handler for the test
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _watch_cases(signal.getsignal(signal.SIGINT))
    finally:
        signal.signal(signal.SIGINT, ignored)


def _watch_cases(before: object) -> None:
    import os

    from nrc.render.wavefront.machine import _InterruptWatch

    caught: list[int] = []

    def swallowing(first_only: bool) -> None:
        """A build that catches KeyboardInterrupt (the first one only, or all) for up to 30 s / 2.5 s."""
        with _InterruptWatch():
            for i in range(300 if first_only else 25):
                try:
                    if i == 0:
                        os.kill(os.getpid(), signal.SIGINT)
                    time.sleep(0.1)
                except KeyboardInterrupt:
                    caught.append(1)
                    if first_only and len(caught) > 1:
                        raise

    import logging

    records: list[str] = []
    torch_log = logging.getLogger("torch._subclasses.fake_tensor")
    sink = logging.Handler()
    sink.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    torch_log.addHandler(sink)
    try:
        with pytest.raises(KeyboardInterrupt):  # raised plainly; what torch logs after the hit is not printed
            with _InterruptWatch() as watch:
                torch_log.error("before")
                try:
                    os.kill(os.getpid(), signal.SIGINT)
                    time.sleep(5)
                except KeyboardInterrupt:
                    torch_log.exception("fake tensor raised TypeError")
                    raise
        torch_log.error("after")
    finally:
        torch_log.removeHandler(sink)
    assert records == ["before", "after"]
    assert watch.hit and signal.getsignal(signal.SIGINT) is before
    with pytest.raises(KeyboardInterrupt):  # turned into another error (as torch's tracing did once)
        with _InterruptWatch():
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(5)
            except KeyboardInterrupt:
                raise TypeError("a tracing error") from None
    with pytest.raises(KeyboardInterrupt):  # the first swallowed: the repeat stops the loop long before its end
        swallowing(first_only=True)
    assert len(caught) == 2 and signal.getsignal(signal.SIGINT) is before
    caught.clear()
    with pytest.raises(KeyboardInterrupt):  # every one swallowed: leaving the block is a stop
        swallowing(first_only=False)
    assert len(caught) >= 2  # (repeated meanwhile)
    with _InterruptWatch() as quiet:
        time.sleep(0.01)
    assert not quiet.hit

    import threading

    class Trap(threading.Event):
        def set(self) -> None:  # a Ctrl-C handled while the block is being left (inside __exit__)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
            super().set()

    class Leaving(_InterruptWatch):
        def __enter__(self):
            super().__enter__()
            self._left = Trap()
            return self

    with pytest.raises(KeyboardInterrupt):  # __exit__ raises it once, and nothing repeats after the block
        with Leaving() as leaving:
            pass
    assert leaving.hit and signal.getsignal(signal.SIGINT) is before
    time.sleep(3 * _InterruptWatch.REPEAT_S)  # a repeat left running would interrupt this sleep
