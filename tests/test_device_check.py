"""``scripts/device_check.sh`` on a machine without CUDA: the dry run, the argument handling, the step runner
(timeouts, failures, the JSON rewritten after every step) and the markdown table."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import pytest

from conftest import REPO

SCRIPT = REPO / "scripts" / "device_check.sh"


def _module():
    spec = importlib.util.spec_from_file_location("device_check", REPO / "scripts" / "device_check.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["device_check"] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


dc = _module()


def _run(*args):
    return subprocess.run(["bash", str(SCRIPT), *map(str, args)], capture_output=True, text=True, timeout=120,
                          env={"PYTHON": sys.executable, "PATH": "/usr/bin:/bin"})


def test_dry_run_lists_every_step_and_what_would_be_skipped(tmp_path):
    proc = _run(tmp_path / "out", "--dry-run")
    assert proc.returncode == 0, proc.stderr
    for name in ("environment", "install", "cuda_tests", "pt_canonical", "nrc_frame_480x270", "nrc_frame_1280x720",
                 "thick_frames_1280x720", "thick_frames_1920x1080", "thick_frames_1920x1080_graphs", "cache_throughput"):
        assert f"\n{name} (timeout" in "\n" + proc.stdout, name
    assert "device=cuda" in proc.stdout and "--no-deps" in proc.stdout
    if not dc.cuda_available():
        assert proc.stdout.count("[would be skipped: no CUDA device") == 8
    assert "Disney cloud is absent" in proc.stdout or "no CUDA" in proc.stdout
    assert not (tmp_path / "out" / "device_check.json").exists()  # nothing ran
    only = _run(tmp_path / "out", "--dry-run", "--only", "cache_throughput")
    assert only.returncode == 0 and "3 steps" in only.stdout and "pt_canonical" not in only.stdout


@pytest.mark.parametrize("args, message", [
    ([], "give OUTDIR"),
    (["OUT", "--only", "nope"], "unknown step(s) nope"),
    (["OUT", "--budget", "-3"], "--budget must be positive"),
    (["OUT", "--budget", "abc"], "invalid float value"),
    (["OUT", "--wheelhouse", "/no/such/dir"], "no such directory"),
    (["--make-wheelhouse", "W", "--python-version", "12"], "--python-version must look like 3.12"),
    (["OUT", "--frobnicate"], "unrecognized arguments"),
])
def test_bad_arguments_give_one_line_and_exit_2(tmp_path, args, message):
    proc = _run(*[str(tmp_path / a) if a in ("OUT", "W") else a for a in args])
    assert proc.returncode == 2
    assert proc.stderr.startswith("device_check: ") and message in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr


def test_missing_vdb_is_noted_and_its_steps_skipped(tmp_path):
    proc = _run(tmp_path / "out", "--dry-run", "--vdb", tmp_path / "absent.vdb")
    assert proc.returncode == 0 and "no such file" in proc.stderr
    step = next(s for s in dc.steps(tmp_path, None, None) if s.name == "pt_canonical")
    assert "Disney cloud is absent" in dc.missing(step, True, None)
    assert dc.missing(step, True, tmp_path / "absent.vdb") is not None
    assert "not installed" in dc.missing(dc.Step("x", "x", [], 1, ("no_such_module_xyz",)), True, None)


def test_steps_run_in_order_with_timeouts_and_the_json_is_rewritten_after_each(tmp_path):
    py = sys.executable
    json_path = tmp_path / "device_check.json"
    # the second step reads the JSON as the runner left it after the first: it must already hold that step
    reads_report = ("import json, sys; d = json.load(open(sys.argv[1])); "
                    "sys.exit(0 if [s['status'] for s in d['steps']] == ['ok'] else 3)")
    plan = [
        dc.Step("first", "prints", [[py, "-c", "print('hello')"]], 30),
        dc.Step("reads", "reads the report", [[py, "-c", reads_report, str(json_path)]], 30,
                parse=lambda o, r: {"walls": len(r["walls_s"]), "x": 1.23456}),
        dc.Step("fails", "exits 4", [[py, "-c", "import sys; print('bad thing'); sys.exit(4)"], [py, "-c", "1"]], 30),
        dc.Step("hangs", "sleeps past its timeout", [[py, "-c", "import time; time.sleep(60)"]], 1),
        dc.Step("needs_gpu", "skipped", [[py, "-c", "1"]], 30, ("cuda",)),
        dc.Step("bad_parse", "figures unreadable", [[py, "-c", "1"]], 30, parse=lambda o, r: 1 / 0),
    ]
    report = dc.Report(tmp_path, {"started": "now", "torch_pin": "2.13.0"})
    rc = dc.execute(plan, report, {"PATH": "/usr/bin:/bin"}, have_cuda=False, vdb=None, budget_s=120)
    assert rc == 1  # a failure and a timeout
    data = json.loads(json_path.read_text())
    status = {s["name"]: s["status"] for s in data["steps"]}
    assert status == {"first": "ok", "reads": "ok", "fails": "failed", "hangs": "timeout", "needs_gpu": "skipped",
                      "bad_parse": "ok"}
    steps = {s["name"]: s for s in data["steps"]}
    assert "hello" in (tmp_path / "first.log").read_text()
    assert steps["reads"]["result"] == {"walls": 1, "x": 1.23456}
    assert "exit code 4" in steps["fails"]["note"] and "bad thing" in steps["fails"]["note"]
    assert len(steps["fails"]["walls_s"]) == 1  # the second command of a failed step does not run
    assert steps["hangs"]["seconds"] < 30 and "killed after 1 s" in steps["hangs"]["note"]
    assert "no CUDA" in steps["needs_gpu"]["note"]
    assert "ZeroDivisionError" in steps["bad_parse"]["note"]
    md = (tmp_path / "device_check.md").read_text()
    rows = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| step")]
    assert [r.split(" | ")[0][2:] for r in rows] == list(status)
    assert "| reads | ok |" in md and "x 1.235" in md and "| hangs | timeout |" in md


def test_budget_skips_what_would_start_after_it(tmp_path):
    py = sys.executable
    plan = [dc.Step("slow", "takes the budget", [[py, "-c", "import time; time.sleep(60)"]], 30),
            dc.Step("late", "starts too late", [[py, "-c", "1"]], 30)]
    report = dc.Report(tmp_path, {})
    assert dc.execute(plan, report, {"PATH": "/usr/bin:/bin"}, False, None, budget_s=1.5) == 1
    steps = report.data["steps"]
    assert steps[0]["status"] == "timeout" and steps[1]["status"] == "skipped"
    assert "budget" in steps[1]["note"]


def test_markdown_escapes_and_rounds():
    text = dc.markdown({"started": "t", "environment": {"gpu": "H200", "torch": "2.11.0", "cuda": "13.0"},
                        "steps": [{"name": "a", "status": "ok", "seconds": 1.234,
                                   "result": {"v": 0.000123456, "n": 3, "nested": {"x": 1}}, "note": "x|y"}]})
    assert "GPU: H200; torch 2.11.0 (CUDA 13.0)" in text
    assert "| a | ok | 1.2 | v 0.0001235; n 3; x\\|y |" in text
