"""One-shot check of nrc on a machine with one NVIDIA GPU: install, CUDA tests, benchmarks; offline.

Run it through ``scripts/device_check.sh OUTDIR`` (it picks the interpreter). Steps, each a subprocess with its own
timeout, all under one overall budget (``--budget``, default 540 s; a step that would start past it is skipped):

1. ``environment``: the interpreter, its torch (which may differ from the project's pin), CUDA and the GPU;
2. ``install``: the project with ``pip install --no-deps``; missing dependencies from ``--wheelhouse DIR`` only
   (never from the network); if the install fails the later steps import the checkout through ``PYTHONPATH``;
3. ``cuda_tests``: ``tests/test_cuda.py`` (eager and compiled step on ``device=cuda`` against the CPU by block
   tests, encodings and the MLP at tight tolerances, the cache's training step, a short NRC run);
4. ``pt_canonical``: the canonical path-tracer benchmark (``+experiment=bench_canonical``) with ``device=cuda``,
   whole process and render alone, twice (the second run loads the compiled step from the cache);
5. ``thick_frames_1280x720``, ``thick_frames_1920x1080``, ``thick_frames_1920x1080_graphs``: the thick cloud's NRC
   frame (trace / infer / train, calls per frame) against the path tracer's 1-spp frame (``scripts/bench_frames.py``),
   the last through CUDA graphs (``renderer.cuda_graphs=true``);
6. ``nrc_frame_480x270``, ``nrc_frame_1280x720``: NRC frames with their trace / infer / train split
   (``scripts/bench_nrc_frame.py``);
7. ``cache_throughput``: the radiance cache's inference / training points/s table (``scripts/bench_cache.py``).

A step whose dependency is missing (CUDA, the Disney cloud given by ``--vdb``, a Python package) is skipped with a
note. ``OUTDIR/device_check.json`` is rewritten after every step (a hang loses nothing before it);
``OUTDIR/device_check.md`` is a short table written at the end; each step's output is in ``OUTDIR/<step>.log``.

Make the wheelhouse beforehand on a connected machine (same platform and Python version as the GPU machine's, or
give ``--python-version`` for another CPython 3.x on x86-64 Linux):

    scripts/device_check.sh --make-wheelhouse wheels/ [--python-version 3.12]
    scripts/device_check.sh OUTDIR [--wheelhouse wheels/] [--vdb ../shared/data/wdas_cloud_sixteenth.vdb]
    scripts/device_check.sh OUTDIR --dry-run       # list the steps, their commands and what would be skipped
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from lab import REPO

# What a run needs besides torch (the project's base dependencies, read from the installed metadata when present)
# and what the checks themselves need; torch is never installed by this script.
RUN_REQUIREMENTS = ["numpy", "openexr", "hydra-core", "tqdm", "pytest"]  # TensorBoard and matplotlib: not needed
ALWAYS = ("environment", "install")  # steps run whatever is missing: they say what is missing
NO_WHEEL = {"torch", "triton"}  # the GPU machine's own builds; never replaced from a wheelhouse
MANYLINUX = ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
             "manylinux1_x86_64"]


class UsageError(Exception):
    """Bad arguments: one line, exit 2."""


@dataclasses.dataclass
class Step:
    """One check: a command run in the repository root with ``timeout_s``; skipped when a need is missing."""

    name: str
    what: str
    commands: list[list[str]]  # run one after the other (each one's whole-process wall time is recorded)
    timeout_s: int
    needs: tuple[str, ...] = ()  # "cuda", "vdb", or Python module names
    parse: Callable[[Path, dict], dict] | None = None  # the step's figures, from OUTDIR and its record


# ------------------------------------------------------------------------------------------------ the report
class Report:
    """The run's JSON, rewritten (atomically) after every step, and its markdown table."""

    def __init__(self, outdir: Path, header: dict):
        self.outdir = outdir
        self.data = {**header, "steps": []}

    @property
    def json_path(self) -> Path:
        return self.outdir / "device_check.json"

    @property
    def md_path(self) -> Path:
        return self.outdir / "device_check.md"

    def add(self, record: dict) -> None:
        self.data["steps"].append(record)
        self.write_json()

    def write_json(self) -> None:
        tmp = self.json_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.data, indent=2, default=str))
        os.replace(tmp, self.json_path)

    def write_markdown(self) -> str:
        text = markdown(self.data)
        self.md_path.write_text(text)
        return text


def _figures(result: dict | None) -> str:
    """A step's headline figures in one cell: ``key value`` pairs, numbers rounded."""
    if not result:
        return ""
    parts = []
    for k, v in result.items():
        if isinstance(v, float):
            v = f"{v:.4g}"
        elif isinstance(v, (dict, list)):
            continue
        parts.append(f"{k} {v}")
    return "; ".join(parts)


def markdown(data: dict) -> str:
    """The summary table of a report's data (``device_check.json``'s content)."""
    env = data.get("environment", {})
    lines = [
        "# nrc device check",
        "",
        f"{data.get('started', '')}; GPU: {env.get('gpu', 'none')}; torch {env.get('torch', '?')} "
        f"(CUDA {env.get('cuda', 'none')}); Python {env.get('python', '?')}; the project pins torch "
        f"{data.get('torch_pin', '?')}.",
        "",
        "| step | status | seconds | figures / note |",
        "|---|---|---|---|",
    ]
    for s in data.get("steps", []):
        cell = _figures(s.get("result"))
        note = s.get("note") or ""
        cell = "; ".join(x for x in (cell, note) if x).replace("|", "\\|").replace("\n", " ")
        secs = s.get("seconds")
        lines.append(f"| {s['name']} | {s['status']} | {'' if secs is None else f'{secs:.1f}'} | {cell} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------ parsers
def _metrics(path: Path) -> dict:
    m = json.loads(path.read_text())
    return {k: m[k] for k in ("backend", "render_seconds", "samples_per_second") if k in m}


def _parse_canonical(outdir: Path, record: dict) -> dict:
    out = {}
    for run, wall in zip(("cold", "warm"), record.get("walls_s", [])):
        out[f"{run}_process_s"] = wall
        metrics = outdir / f"pt_canonical_{run}" / "metrics.json"
        if metrics.is_file():
            for k, v in _metrics(metrics).items():
                out[f"{run}_{k}"] = v
    return out


def _parse_json(name: str) -> Callable[[Path, dict], dict]:
    def parse(outdir: Path, record: dict) -> dict:
        data = json.loads((outdir / f"{name}.json").read_text())
        flat = {}
        for k, v in data.items():
            if isinstance(v, dict):
                flat.update({f"{k}_{kk}": vv for kk, vv in v.items() if not isinstance(vv, (dict, list))})
            elif not isinstance(v, list):
                flat[k] = v
        return flat

    return parse


def _parse_junit(outdir: Path, record: dict) -> dict:
    import xml.etree.ElementTree as ET

    root = ET.parse(outdir / "cuda_tests.xml").getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    keys = ("tests", "failures", "errors", "skipped")
    return {k: int(suite.get(k, 0)) for k in keys}


# ------------------------------------------------------------------------------------------------ the steps
def steps(outdir: Path, vdb: Path | None, wheelhouse: Path | None) -> list[Step]:
    py = sys.executable
    out = []
    out.append(Step("environment", "interpreter, torch, CUDA and GPU",
                    [[py, str(Path(__file__).resolve()), "--probe-environment", str(outdir / "environment.json")]],
                    60, parse=lambda o, r: json.loads((o / "environment.json").read_text())))
    install = [[py, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index", "-e", str(REPO)]]
    if wheelhouse is not None:  # pip keeps what is already installed and takes only the missing ones from the DIR
        install.insert(0, [py, "-m", "pip", "install", "-q", "--no-index", "--find-links", str(wheelhouse),
                           *RUN_REQUIREMENTS])
    out.append(Step("install", "the project (--no-deps); missing dependencies from the wheelhouse", install, 240))
    out.append(Step("cuda_tests", "tests/test_cuda.py: eager and compiled step, encodings, MLP, training, NRC",
                    [[py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cuda", "tests/test_cuda.py",
                      f"--junitxml={outdir / 'cuda_tests.xml'}", "-o", "addopts=", "--durations=10"]],
                    300, ("cuda", "pytest", "hydra", "OpenEXR"), _parse_junit))
    vdb_arg = str(vdb) if vdb else "MISSING"
    canonical = [[py, "-m", "nrc", "+experiment=bench_canonical", "device=cuda", f"scene.volume.path={vdb_arg}",
                  f"hydra.run.dir={outdir / f'pt_canonical_{run}'}"] for run in ("cold", "warm")]
    out.append(Step("pt_canonical", "canonical path-tracer benchmark (128x72, 512 spp), cold then warm cache",
                    canonical, 240, ("cuda", "vdb", "hydra", "OpenEXR"), _parse_canonical))
    # frames bounded by work: NRC against pt's 1-spp frame, without and with CUDA graphs (renderer.cuda_graphs)
    for w, h, graphs, t in ((1280, 720, False, 200), (1920, 1080, False, 240), (1920, 1080, True, 240)):
        name = f"thick_frames_{w}x{h}" + ("_graphs" if graphs else "")
        out.append(Step(name, f"the thick cloud at {w}x{h}: NRC frame (trace / infer / train, calls) and pt 1 spp"
                        + (", through CUDA graphs" if graphs else ""), [[
            py, str(REPO / "scripts" / "bench_frames.py"), "--width", str(w), "--height", str(h), "--frames", "8",
            "--skip", "3", "--pt-repeats", "3", "--device", "cuda", "--vdb", vdb_arg,
            "--json", str(outdir / f"{name}.json"), *(["renderer.cuda_graphs=true"] if graphs else [])]],
            t, ("cuda", "vdb", "hydra", "OpenEXR"), _parse_json(name)))
    for w, h, t in ((480, 270, 150), (1280, 720, 200)):
        name = f"nrc_frame_{w}x{h}"
        out.append(Step(name, f"NRC frames at {w}x{h}: trace / infer / train", [[
            py, str(REPO / "scripts" / "bench_nrc_frame.py"), "--width", str(w), "--height", str(h), "--frames", "8",
            "--vdb", vdb_arg, "--json", str(outdir / f"{name}.json"), "device=cuda"]],
            t, ("cuda", "vdb", "hydra", "OpenEXR"), _parse_json(name)))
    out.append(Step("cache_throughput", "radiance cache inference / training points/s per encoding and MLP shape", [[
        py, str(REPO / "scripts" / "bench_cache.py"), "--device", "cuda", "--reps", "3", "--no-write",
        "--markdown", str(outdir / "cache_throughput.md")]], 180, ("cuda",),
        lambda o, r: {"table": "cache_throughput.md"}))
    return out


def probe_environment(path: Path) -> None:
    """The interpreter, its torch, CUDA and the GPU, to ``path`` (JSON) and stdout; never raises for a missing
    piece (the report says what is missing)."""
    import platform

    info: dict = {"python": platform.python_version(), "executable": sys.executable, "machine": platform.machine()}
    try:
        import torch

        info["torch"] = torch.__version__
        info["cuda"] = torch.version.cuda
        info["cuda_available"] = torch.cuda.is_available()
        if torch.cuda.is_available():
            p = torch.cuda.get_device_properties(0)
            info["gpu"] = p.name
            info["gpu_memory_gib"] = round(p.total_memory / 2**30, 1)
    except Exception as e:  # noqa: BLE001
        info["torch_error"] = f"{type(e).__name__}: {e}"
    try:
        smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20)
        info["nvidia_smi"] = smi.stdout.strip() or smi.stderr.strip()
    except (OSError, subprocess.TimeoutExpired) as e:
        info["nvidia_smi"] = f"unavailable ({type(e).__name__})"
    path.write_text(json.dumps(info, indent=2))
    print(json.dumps(info))




def missing(step: Step, have_cuda: bool, vdb: Path | None) -> str | None:
    """Why ``step`` cannot run here, or None (the ``ALWAYS`` steps run whatever is missing)."""
    if step.name in ALWAYS:
        return None
    for need in step.needs:
        if need == "cuda" and not have_cuda:
            return "no CUDA device visible to this interpreter's torch"
        if need == "vdb" and (vdb is None or not vdb.is_file()):
            return "the Disney cloud is absent (give --vdb PATH)"
        if need not in ("cuda", "vdb") and importlib.util.find_spec(need) is None:
            return f"Python package {need!r} is not installed (add it to the wheelhouse)"
    return None


def cuda_available() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return torch.cuda.is_available()


def torch_pin() -> str:
    text = (REPO / "pyproject.toml").read_text()
    m = re.search(r'"torch==([^"]+)"', text)
    return m.group(1) if m else "?"


# ------------------------------------------------------------------------------------------------ running
def run_step(step: Step, outdir: Path, env: dict, timeout_s: float) -> dict:
    """Run ``step``'s commands in order (output to ``OUTDIR/<step>.log``) within ``timeout_s`` in all."""
    log = outdir / f"{step.name}.log"
    t0 = time.perf_counter()
    walls, status, note = [], "ok", None
    with open(log, "w") as f:
        for command in step.commands:
            f.write(f"$ {shlex.join(command)}\n")
            f.flush()
            left = timeout_s - (time.perf_counter() - t0)
            t_cmd = time.perf_counter()
            proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=f, stderr=subprocess.STDOUT,
                                    start_new_session=True)
            try:
                rc = proc.wait(timeout=max(left, 1.0))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, 9)
                proc.wait()
                status, note = "timeout", f"killed after {timeout_s:.0f} s"
                break
            walls.append(time.perf_counter() - t_cmd)
            if rc != 0:
                f.flush()
                status, note = "failed", f"exit code {rc}; last lines: {_tail(log)}"
                break
    record = {"name": step.name, "what": step.what, "status": status, "seconds": time.perf_counter() - t0,
              "timeout_s": round(timeout_s), "commands": [shlex.join(c) for c in step.commands], "walls_s": walls,
              "log": log.name, "note": note}
    if step.parse is not None:
        try:
            record["result"] = step.parse(outdir, record)
        except Exception as e:  # noqa: BLE001 -- a step's output that cannot be read is noted, not fatal
            if status == "ok":
                record["note"] = f"no figures: {type(e).__name__}: {e}"
    return record


def _tail(log: Path, n: int = 3) -> str:
    lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    return " / ".join(lines[-n:])[-400:]


def check(outdir: Path, vdb: Path | None, wheelhouse: Path | None, budget_s: float, dry_run: bool,
          only: list[str] | None) -> int:
    outdir.mkdir(parents=True, exist_ok=True)
    plan = steps(outdir, vdb, wheelhouse)
    if only:
        unknown = sorted(set(only) - {s.name for s in plan})
        if unknown:
            raise UsageError(f"--only: unknown step(s) {', '.join(unknown)}; steps: {', '.join(s.name for s in plan)}")
        plan = [s for s in plan if s.name in only or s.name in ALWAYS]
    have_cuda = cuda_available()
    if dry_run:
        for s in plan:
            why = missing(s, have_cuda, vdb)
            print(f"{s.name} (timeout {s.timeout_s} s){'  [would be skipped: ' + why + ']' if why else ''}\n"
                  f"    {s.what}")
            for c in s.commands:
                print(f"    $ {shlex.join(c)}")
        print(f"{len(plan)} steps; overall budget {budget_s:.0f} s; output in {outdir}")
        return 0
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(x for x in (str(REPO), env.get("PYTHONPATH")) if x)
    env.setdefault("TORCHINDUCTOR_CACHE_DIR", str(outdir / "inductor"))
    report = Report(outdir, {"started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "torch_pin": torch_pin(),
                             "budget_s": budget_s, "vdb": str(vdb) if vdb else None,
                             "wheelhouse": str(wheelhouse) if wheelhouse else None})
    return execute(plan, report, env, have_cuda, vdb, budget_s)


def execute(plan: list[Step], report: Report, env: dict, have_cuda: bool, vdb: Path | None, budget_s: float) -> int:
    """Run ``plan`` in order under the overall budget, the report's JSON rewritten after every step and its
    markdown written at the end; 1 if a step failed or timed out, else 0 (skipped steps are not failures)."""
    report.write_json()
    deadline = time.perf_counter() + budget_s
    for s in plan:
        left = deadline - time.perf_counter()
        why = missing(s, have_cuda, vdb)
        if why is None and left < 1:
            why = f"the overall budget ({budget_s:.0f} s) is spent"
        if why is not None:
            report.add({"name": s.name, "what": s.what, "status": "skipped", "seconds": None, "note": why})
            print(f"[device_check] {s.name}: skipped ({why})", flush=True)
            continue
        print(f"[device_check] {s.name}: {s.what} (timeout {min(s.timeout_s, left):.0f} s)", flush=True)
        record = run_step(s, report.outdir, env, min(s.timeout_s, left))
        if s.name == "environment" and record.get("result"):
            report.data["environment"] = record["result"]
        if s.name == "install" and record["status"] != "ok":
            record["note"] = (record.get("note") or "") + "; the checkout is imported through PYTHONPATH instead"
        report.add(record)
        print(f"[device_check] {s.name}: {record['status']} in {record['seconds']:.1f} s"
              f"{' -- ' + record['note'] if record.get('note') else ''}", flush=True)
    print(report.write_markdown())
    failed = [s["name"] for s in report.data["steps"] if s["status"] in ("failed", "timeout")]
    return 1 if failed else 0


# ------------------------------------------------------------------------------------------------ wheelhouse
def requirement_closure(roots: list[str]) -> list[tuple[str, str]]:
    """``(name, version)`` of ``roots`` and everything they require, as installed in this interpreter (extras and
    requirements whose markers do not hold here are left out; torch and its own dependencies too)."""
    from packaging.requirements import Requirement

    torch_deps = set()
    try:
        for r in importlib.metadata.requires("torch") or []:
            req = Requirement(r)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                torch_deps.add(_norm(req.name))
    except importlib.metadata.PackageNotFoundError:
        pass
    seen: dict[str, str] = {}
    todo = list(roots)
    while todo:
        name = _norm(todo.pop())
        if name in seen or name in NO_WHEEL:
            continue
        try:
            dist = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError:
            raise UsageError(f"--make-wheelhouse: {name} is not installed in {sys.executable}; install the project "
                             "with pip install -e '.[dev]' first") from None
        seen[name] = dist.version
        for r in dist.requires or []:
            req = Requirement(r)
            if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                continue
            if _norm(req.name) not in torch_deps:
                todo.append(req.name)
    return sorted(seen.items())


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def make_wheelhouse(dest: Path, python_version: str | None) -> int:
    """Wheels of what a check needs besides torch, pinned to this interpreter's versions."""
    dest.mkdir(parents=True, exist_ok=True)
    pins = [f"{n}=={v}" for n, v in requirement_closure(RUN_REQUIREMENTS)]
    print(f"[device_check] {len(pins)} packages: {' '.join(pins)}", flush=True)
    base = [sys.executable, "-m", "pip"]
    for pin in pins:
        cmd = base + ["download", "-q", "--no-deps", "--only-binary=:all:", "-d", str(dest), pin]
        if python_version:
            cmd += ["--python-version", python_version, "--implementation", "cp"]
            for p in MANYLINUX:
                cmd += ["--platform", p]
        if subprocess.run(cmd, capture_output=True).returncode != 0:  # a pure-Python sdist (antlr4): build a wheel
            if subprocess.run(base + ["wheel", "-q", "--no-deps", "-w", str(dest), pin]).returncode != 0:
                print(f"[device_check] no wheel for {pin}", file=sys.stderr)
                return 1
    size = sum(p.stat().st_size for p in dest.glob("*.whl")) / 2**20
    print(f"[device_check] wheelhouse {dest}: {len(list(dest.glob('*.whl')))} wheels, {size:.1f} MiB")
    return 0


# ------------------------------------------------------------------------------------------------ command line
def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="device_check.sh", description=__doc__.split("\n\n")[0])
    ap.add_argument("outdir", nargs="?", type=Path, help="where the JSON, markdown and logs go")
    ap.add_argument("--wheelhouse", type=Path, help="wheels of the missing dependencies (offline install)")
    ap.add_argument("--vdb", type=Path, help="the Disney cloud (steps that need it are skipped without it)")
    ap.add_argument("--budget", type=float, default=540.0, help="overall seconds (default 540)")
    ap.add_argument("--only", help="comma-separated steps to run (environment and install always run)")
    ap.add_argument("--dry-run", action="store_true", help="list the steps and what would be skipped; run nothing")
    ap.add_argument("--make-wheelhouse", type=Path, metavar="DIR", help="download / build the wheels and exit")
    ap.add_argument("--python-version", help="with --make-wheelhouse: the GPU machine's Python (e.g. 3.12)")
    ap.add_argument("--probe-environment", type=Path, help=argparse.SUPPRESS)

    def error(message: str) -> None:
        raise UsageError(message)

    ap.error = error  # type: ignore[method-assign]
    args = ap.parse_args(argv)
    if args.make_wheelhouse is None and args.outdir is None and args.probe_environment is None:
        raise UsageError("give OUTDIR (or --make-wheelhouse DIR)")
    if args.budget <= 0:
        raise UsageError(f"--budget must be positive, got {args.budget}")
    if args.wheelhouse is not None and not args.wheelhouse.is_dir():
        raise UsageError(f"--wheelhouse {args.wheelhouse}: no such directory")
    if args.vdb is not None and not args.vdb.is_file():
        print(f"[device_check] --vdb {args.vdb}: no such file; the steps that need it are skipped", file=sys.stderr)
        args.vdb = None
    if args.python_version and not re.fullmatch(r"3\.\d+", args.python_version):
        raise UsageError(f"--python-version must look like 3.12, got {args.python_version!r}")
    return args


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse_args(sys.argv[1:] if argv is None else argv)
        if args.probe_environment is not None:
            probe_environment(args.probe_environment)
            return 0
        if args.make_wheelhouse is not None:
            return make_wheelhouse(args.make_wheelhouse, args.python_version)
        only = [s.strip() for s in args.only.split(",") if s.strip()] if args.only else None
        vdb = args.vdb.resolve() if args.vdb else None
        return check(args.outdir.resolve(), vdb, args.wheelhouse.resolve() if args.wheelhouse else None,
                     args.budget, args.dry_run, only)
    except UsageError as e:
        print(f"device_check: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
