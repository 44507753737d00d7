"""Sweeps that share a machine (``threads``, ``nrc.app.SweepSetup``): each job's thread count follows the
launcher's jobs at once and lands in ``metrics.json``; the compiled step is built once, before the jobs, for
that count."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
from omegaconf import OmegaConf

from conftest import REPO
from nrc import app
from nrc.config import THREADS_ENV, job_threads
from nrc.errors import ConfigError

JOBLIB = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
LOCAL = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
SLURM = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
BASIC = "hydra._internal.core_plugins.basic_launcher.BasicLauncher"


@pytest.fixture
def keep_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


@pytest.mark.parametrize("target, n_jobs, jobs, cores, expected", [
    (JOBLIB, 2, 4, 8, 2), (JOBLIB, -1, 4, 8, 4), (JOBLIB, -1, 16, 8, 8), (JOBLIB, -2, 16, 8, 7),
    (JOBLIB, 3, 2, 8, 2), (LOCAL, None, 3, 8, 3), (SLURM, None, 3, 8, None), (BASIC, None, 3, 8, None),
])
def test_jobs_at_once_follow_the_launcher(target, n_jobs, jobs, cores, expected):
    launcher = OmegaConf.create({"_target_": target, **({"n_jobs": n_jobs} if n_jobs is not None else {})})
    assert app.concurrent_jobs(launcher, jobs, cores) == expected


def test_threads_setting(monkeypatch):
    monkeypatch.delenv(THREADS_ENV, raising=False)
    monkeypatch.delenv("SLURM_CPUS_PER_TASK", raising=False)
    assert job_threads("auto") == torch.get_num_threads() and job_threads(3) == 3
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "6")
    assert job_threads("auto") == 6
    monkeypatch.setenv(THREADS_ENV, "2")
    assert job_threads("auto") == 2 and job_threads(5) == 5  # an explicit count wins
    for bad in (0, -1, "many", 1.5, True):
        with pytest.raises(ConfigError, match="threads must be a positive integer or auto"):
            job_threads(bad)


def test_the_sweep_expands_to_its_jobs():
    task = ["scene.integrator.spp=1,2", "encoding=hashgrid_oneblob,triangle_oneblob", "frames=3"]
    jobs = app.sweep_jobs(OmegaConf.create({"hydra": {"overrides": {"task": task}}}))
    assert len(jobs) == 4 and ["scene.integrator.spp=2", "encoding=triangle_oneblob", "frames=3"] in jobs


def test_prebuild_compiles_each_job_at_its_thread_count(monkeypatch, keep_threads):
    """The launching process renders the first job of each step structure tiny with the compiled backend at the
    job's thread count (two encodings: one structure); eager jobs and bad configs are skipped, a reference job's own
    keys dropped (the compile itself: the compiled-step tests)."""
    built = []
    monkeypatch.setattr(app, "execute", lambda cfg, out, progress: built.append(
        (cfg.renderer.name, cfg.renderer.backend, cfg.threads, cfg.scene.camera.width, cfg.get("frames"))))
    monkeypatch.setenv(THREADS_ENV, "1")
    monkeypatch.setattr(app, "step_of", lambda cfg, real=app.step_of: (real(cfg)[0], False, None))  # none cached
    app.prebuild_steps([["renderer=nrc", "encoding=triangle_oneblob"], ["renderer=nrc", "encoding=identity"],
                        ["renderer=pt", "threads=2"],
                        ["renderer=pt", "renderer.backend=eager"], ["scene.nope=1"],
                        ["renderer=pt", "reference.chunks=0:4"]])
    assert built == [("nrc", "compiled", 1, 8, 1), ("pt", "compiled", 2, 8, 1), ("pt", "compiled", 1, 8, 1)]


def test_a_sweep_run_again_finds_its_steps_without_building_renderers(monkeypatch, keep_threads, tmp_path):
    """The packages a job needs are recorded after the first sweep; the next sweep checks their files instead of
    building each job's renderer, and builds again when a file is gone."""
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(THREADS_ENV, "1")
    package = tmp_path / "nrc-aot" / "x-track.pt2"
    package.parent.mkdir(parents=True)
    package.write_bytes(b"")
    calls = []

    def step_of(cfg):
        calls.append(cfg.renderer.name)
        return ("key",), True, (package,)

    monkeypatch.setattr(app, "step_of", step_of)
    monkeypatch.setattr(app, "execute", lambda *a, **k: pytest.fail("nothing to build: all cached"))
    jobs = [["renderer=pt"], ["renderer=pt", "scene.volume.albedo=0.5"]]
    app.prebuild_steps(jobs)
    assert calls == ["pt", "pt"]  # two configs, one structure: both recorded
    memo = json.loads((tmp_path / "nrc-aot" / "sweep-steps.json").read_text())
    assert list(memo.values()) == [[str(package)], [str(package)]]
    app.prebuild_steps(jobs)
    assert calls == ["pt", "pt"]  # the second sweep built no renderer
    package.unlink()
    app.prebuild_steps(jobs[:1])
    assert calls == ["pt", "pt", "pt"]  # a package gone: the renderer is built to find out


KNOWN_SWEEP = r"""
import json, os, sys
from pathlib import Path
os.environ["TORCHINDUCTOR_CACHE_DIR"] = sys.argv[1]
os.environ["NRC_THREADS"] = "1"
from nrc import app
from nrc.config import absolute_paths, compose
cores = app.default_threads()
jobs = [["renderer=pt"], ["renderer=nrc", "encoding=triangle_oneblob"]]
package = Path(sys.argv[1]) / "nrc-aot" / "x-track.pt2"
if sys.argv[2] == "first":  # a sweep recorded these jobs' packages
    package.write_bytes(b"")
    memo = json.loads((package.parent / "sweep-steps.json").read_text())
    for job in jobs:
        tiny = compose([*job, *app.PREBUILD_OVERRIDES, "threads=1"])
        absolute_paths(tiny)
        memo[app._known_key(tiny, 1)] = [str(package)]
    (package.parent / "sweep-steps.json").write_text(json.dumps(memo))
else:
    app.prebuild_steps(jobs)
print(cores, "torch" in sys.modules)
"""


def test_a_sweep_whose_steps_are_known_launches_without_importing_torch(tmp_path):
    """The launching process of a sweep run again reads torch's thread count and the jobs' packages from the
    sweeps' memory and imports no torch (its workers do): ~1.4 s of a sweep's wall time."""
    def run(which):
        out = subprocess.run([sys.executable, "-c", KNOWN_SWEEP, str(tmp_path), which], capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.split()

    cores, imported = run("first")
    assert int(cores) >= 1 and imported == "True"  # the first asks torch (a fresh process: its default count)
    assert run("again") == [cores, "False"]


@pytest.mark.slow
def test_a_joblib_sweeps_workers_get_cores_over_jobs_threads(tmp_path):
    cores = int(subprocess.run([sys.executable, "-c", "import torch; print(torch.get_num_threads())"],
                               capture_output=True, text=True, check=True).stdout)
    proc = subprocess.run([sys.executable, "-m", "nrc", "-m", "scene.integrator.seed=1,2", "hydra/launcher=joblib",
                           "hydra.launcher.n_jobs=2", "renderer.backend=eager", "scene.camera.width=8",
                           "scene.camera.height=4", "scene.volume.procedural.resolution=16", "denoise=none",
                           f"hydra.sweep.dir={tmp_path}"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    threads = [json.loads((tmp_path / str(i) / "metrics.json").read_text())["threads"] for i in range(2)]
    assert threads == [max(1, cores // 2)] * 2
