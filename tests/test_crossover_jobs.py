"""The crossover map's points as jobs (``scripts/crossover_map.py --jobs``): each point's summary records its node
and machine type; the map refuses to mix machine types and refuses a job without its reference."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import REPO, SHARED_VDB, load_script

TINY = ["--points", "d0.35", "--width", "12", "--height", "8", "--warmup", "2", "--frames", "2", "--pt-spp", "1",
        "--nrc-spp", "1", "--ref-spp", "2", "--pt", "renderer=pt,renderer.backend=eager",
        "--nrc", "renderer=nrc,renderer.backend=eager,renderer.log.tensorboard=false"]


def test_mixed_machine_types_are_refused():
    from lab.jobs import check_one_machine_type

    one = {"meta": {"machine_type": "CPU A, 2 cores, 2 threads, torch 2.13.0"}}
    other = {"meta": {"machine_type": "CPU B, 32 cores, 32 threads, torch 2.13.0"}}
    check_one_machine_type({"d2": one, "d5": one}, "crossover_map")
    with pytest.raises(SystemExit, match=r"crossover_map: .*d2, d5 on CPU A.*; d10 on CPU B"):
        check_one_machine_type({"d2": one, "d5": one, "d10": other}, "crossover_map")


def test_slurm_parameters_and_bad_ones():
    from lab.jobs import run_commands, slurm_parameters

    assert slurm_parameters(["partition=cpu", "cpus_per_task=32", "timeout_min=30"]) == {
        "slurm_exclusive": True, "timeout_min": 30, "slurm_partition": "cpu", "cpus_per_task": 32}
    with pytest.raises(SystemExit, match="--slurm 'partition': expected KEY=VALUE"):
        slurm_parameters(["partition"])
    with pytest.raises(SystemExit, match="unknown kind 'pbs'"):
        run_commands({"a": ["true"]}, "pbs", REPO / "outputs", REPO)


def test_the_cold_start_picks_nrc_at_its_last_frame():
    cm = load_script("crossover_map")
    eq = [{"config": "nrc+oidn", "baseline": "pt+oidn", "mode": "single", "frames": 1, "ratio_rel_mse_medium_corr": 0.5},
          *({"config": "nrc+oidn", "baseline": "pt+oidn", "mode": "accumulate", "frames": n,
             "ratio_rel_mse_medium_corr": r} for n, r in ((16, 0.9), (30, 1.2), (8, 0.7)))]
    assert cm.pick({"equal_time": eq}, "nrc+oidn", "pt+oidn")["mode"] == "single"
    assert cm.pick({"equal_time": eq}, "nrc+oidn", "pt+oidn", cold=True)["frames"] == 30


def crossover(tmp_path, *args):
    env = {**os.environ, "NRC_REFERENCE_DIR": str(tmp_path / "refs")}
    return subprocess.run([sys.executable, str(REPO / "scripts" / "crossover_map.py"), "--out", str(tmp_path / "map"),
                           *TINY, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_VDB.is_file(), reason="the Disney cloud is absent")
def test_a_point_as_a_local_job_then_the_map_refuses_another_machine_type(tmp_path):
    proc = crossover(tmp_path, "--jobs", "local")  # no reference yet: refused, with the command that renders it
    assert proc.returncode != 0 and "python -m nrc.reference_app" in proc.stderr, proc.stderr[-2000:]
    env = {**os.environ, "NRC_REFERENCE_DIR": str(tmp_path / "refs")}
    ref = subprocess.run([sys.executable, "-m", "nrc.reference_app", "scene=thick",
                          "scene.volume.path=../shared/data/wdas_cloud_sixteenth.vdb", "scene.camera.width=12",
                          "scene.camera.height=8", "scene.volume.density_scale=0.35", "scene.integrator.spp=2",
                          "reference.chunk_spp=1", "renderer.backend=eager", f"hydra.run.dir={tmp_path / 'run'}"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert ref.returncode == 0, ref.stderr[-2000:]
    proc = crossover(tmp_path, "--jobs", "local")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "[d0.35] local job" in proc.stdout
    point = json.loads((tmp_path / "map" / "map.json").read_text())["points"][0]
    assert point["node"] and "threads" in point["machine_type"]
    summary = tmp_path / "map" / "d0.35" / "summary.json"
    s = json.loads(summary.read_text())
    s["meta"]["machine_type"] = "another CPU"
    summary.write_text(json.dumps(s))
    import shutil

    shutil.copytree(tmp_path / "map" / "d0.35", tmp_path / "map" / "d0.6")  # a second point, on this machine type
    s["meta"]["machine_type"] = point["machine_type"]
    (tmp_path / "map" / "d0.6" / "summary.json").write_text(json.dumps(s))
    proc = crossover(tmp_path, "--points", "d0.35,d0.6")
    assert proc.returncode != 0 and "different machine types" in proc.stderr
