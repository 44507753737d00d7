"""The README's ``python -m nrc`` commands: each composes and passes the app's checks (default set), and each runs
at a tiny size (long set), so the front door never shows a command that fails."""

from __future__ import annotations

import itertools
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, compose

TINY = ["scene.camera.width=16", "scene.camera.height=9", "scene.integrator.spp=1", "frames=2"]


def readme_commands() -> list[list[str]]:
    """The argument lists of every ``python -m nrc`` command in the README's code blocks (comments dropped)."""
    text = (REPO / "README.md").read_text()
    out = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.splitlines():
            if "python -m nrc" not in line:
                continue
            args = shlex.split(line.split("python -m nrc", 1)[1], comments=True)
            out.append(args)
    return out


COMMANDS = readme_commands()


def jobs(args: list[str]) -> list[list[str]]:
    """The overrides of each job the command starts (a ``-m`` sweep: every combination)."""
    overrides = [a for a in args if a not in ("-m", "--multirun") and not a.startswith("hydra/")]
    if "-m" not in args and "--multirun" not in args:
        return [overrides]
    choices = [[f"{o.split('=', 1)[0]}={v}" for v in o.split("=", 1)[1].split(",")] for o in overrides]
    return [list(c) for c in itertools.product(*choices)]


def test_the_readme_has_its_commands():
    assert len(COMMANDS) >= 5 and ["renderer=nrc", "frames=30"] in COMMANDS


@pytest.mark.parametrize("args", COMMANDS, ids=lambda a: " ".join(a)[:50])
def test_readme_command_composes_and_passes_the_checks(args, tmp_path, monkeypatch):
    from nrc import app

    monkeypatch.chdir(REPO)
    for overrides in jobs(args):
        cfg = compose(overrides)
        app.absolute_paths(cfg)
        # the files the command names, and the volume its scene preset names (scene=thick: the shared Disney cloud)
        files = [REPO / v.split("=", 1)[1] for v in overrides if v.endswith((".exr", ".vdb", ".npz"))]
        if cfg.scene.volume.get("source") in ("vdb", "npz"):
            files.append(Path(cfg.scene.volume.path))
        if all(f.is_file() for f in files):  # a clone without ../shared/data beside it checks the rest
            app.preflight(cfg)


@pytest.mark.slow
@pytest.mark.parametrize("args", COMMANDS, ids=lambda a: " ".join(a)[:50])
def test_readme_command_runs_at_a_tiny_size(args, tmp_path):
    from nrc.io import write_exr

    args = list(args)
    for i, a in enumerate(args):
        if a.endswith("path=my_sky.exr"):  # the user's own sky: a made one
            write_exr(tmp_path / "my_sky.exr", np.full((8, 16, 3), 0.5, np.float32))
            args[i] = a.replace("my_sky.exr", str(tmp_path / "my_sky.exr"))
        if a.endswith(".vdb") and not (REPO / a.split("=", 1)[1]).is_file():
            pytest.skip(f"{a.split('=', 1)[1]} is absent")
    sweep = "-m" in args
    where = f"hydra.sweep.dir={tmp_path / 'sweep'}" if sweep else f"hydra.run.dir={tmp_path / 'run'}"
    # a sweep: eager (the launching process would compile the step for the workers first, minutes: that build is
    # tested in tests/test_sweeps.py and timed in docs/measurements/speed.md)
    extra = ["renderer.backend=eager"] if sweep else []
    proc = subprocess.run([sys.executable, "-m", "nrc", *args, *TINY, *extra, where], cwd=REPO, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    images = list(tmp_path.rglob("image.exr"))
    assert len(images) == (len(jobs(args)) if sweep else 1)
