"""Measurements as launcher jobs: the points of ``scripts/crossover_map.py`` and the configurations of
``scripts/speed_vs_error.py``, each its own submitit job (``pip install -e '.[cluster]'``).

Equal-time ratios compare times measured in different jobs, so they hold only when every job had a machine of one
type to itself: ``local`` runs the jobs one after another on this machine, ``slurm`` gives each a node of its own
(``--exclusive``), and the results say where they ran (:func:`lab.machine.machine`, the node, the threads); a
report built from them refuses to mix machine types (:func:`check_one_machine_type`).
"""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path

JOB_KINDS = ("local", "slurm")
SLURM_GENERIC = ("timeout_min", "cpus_per_task", "mem_gb", "nodes", "tasks_per_node", "name")


def check_one_machine_type(summaries: dict[str, dict], what: str) -> None:
    """Refuse results of ``summaries`` (name -> a summary with ``meta.machine_type``) measured on different machine
    types (CPU model, cores, threads, torch): equal-time ratios cannot mix them. ``what`` names the caller."""
    kinds: dict[str, list[str]] = {}
    for name, s in summaries.items():
        meta = s.get("meta", {})
        kinds.setdefault(meta.get("machine_type") or meta.get("machine") or "unknown", []).append(name)
    if len(kinds) > 1:
        raise SystemExit(f"{what}: the results were measured on different machine types, which equal-time ratios "
                         "cannot mix: " + "; ".join(f"{', '.join(v)} on {k}" for k, v in kinds.items())
                         + " (re-run the odd ones out on one type: delete their results)")


def without_jobs(argv: list[str]) -> list[str]:
    """``argv`` without ``--jobs`` / ``--slurm`` and their values: a tool's command line as its jobs run it."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a in ("--jobs", "--slurm"):
            skip = True
        elif not a.startswith(("--jobs=", "--slurm=")):
            out.append(a)
    return out


def _run_command(cmd: list[str], cwd: str) -> str:
    """One measurement, inside its job; returns the node it ran on."""
    subprocess.run(cmd, cwd=cwd, check=True)
    return platform.node()


def slurm_parameters(items: list[str]) -> dict:
    """``KEY=VALUE`` strings as submitit parameters: an exclusive node and 2 h unless given; submitit's generic
    keys as they are, the others as ``slurm_<key>``."""
    params: dict = {"slurm_exclusive": True, "timeout_min": 120}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--slurm {item!r}: expected KEY=VALUE (e.g. partition=cpu)")
        params[key if key in SLURM_GENERIC else f"slurm_{key}"] = int(value) if value.isdigit() else value
    return params


def run_commands(todo: dict[str, list[str]], kind: str, folder: Path, cwd: Path,
                 slurm: list[str] | None = None) -> dict[str, str]:
    """Run each command of ``todo`` (name -> argv) as a job of ``kind`` (``local``: one at a time, each with the
    machine to itself; ``slurm``: all submitted, a node each) with logs under ``folder``; returns name -> node.
    A failed job raises ``SystemExit`` naming it and its log folder."""
    if kind not in JOB_KINDS:
        raise SystemExit(f"jobs: unknown kind {kind!r} (known: {', '.join(JOB_KINDS)})")
    try:
        import cloudpickle
        import submitit
    except ImportError:
        raise SystemExit("jobs: running measurements as jobs needs submitit: pip install -e '.[cluster]'") from None
    # the job's Python has no scripts/ on its path: this module travels in the job's pickle, not by its name
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    if kind == "local":
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=24 * 60)
    else:
        executor = submitit.AutoExecutor(folder=folder, cluster="slurm")
        executor.update_parameters(**slurm_parameters(slurm or []))
    nodes: dict[str, str] = {}

    def wait(name: str, job) -> None:
        try:
            nodes[name] = job.result()
        except Exception as err:  # noqa: BLE001 -- submitit raises its own FailedJobState, UncompletedJobError
            raise SystemExit(f"jobs: {name} failed ({type(err).__name__}); its log: {job.paths.stderr}") from None
        print(f"[{name}] done on {nodes[name]}", flush=True)

    if kind == "local":  # one at a time: equal-time measurements need the machine to themselves
        for name, cmd in todo.items():
            job = executor.submit(_run_command, cmd, str(cwd))
            print(f"[{name}] local job {job.job_id}", flush=True)
            wait(name, job)
        return nodes
    jobs = {name: executor.submit(_run_command, cmd, str(cwd)) for name, cmd in todo.items()}
    for name, job in jobs.items():
        print(f"[{name}] slurm job {job.job_id}", flush=True)
    for name, job in jobs.items():
        wait(name, job)
    return nodes
