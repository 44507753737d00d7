"""An NRC frame against a path-traced 1-spp frame, both from this commit in the same minutes (docs/measurements/nrc_frames.md,
"Frames bounded by work").

Renders ``--frames`` NRC frames (``scene.integrator.spp=1`` a frame) of a scene type and ``--pt-repeats`` path-traced
1-spp images of the same scene (new seeds each), and prints, per renderer, the median, p95 and maximum frame time
(NRC: frames ``--skip`` .. ``--frames``-1; carried training paths make its frames uneven), NRC's trace / infer /
train split (train: what the frame waited for; its steps' own time apart, run beside the next frame's trace with
``renderer.training.overlap``), the step calls per frame, the milliseconds per call, the scattering events per frame
and the trace's cost per event. Start-up (compile or cache load) is reported apart, with the whole process's time. Not a test: speed
lives here and in docs/measurements/nrc_frames.md.

    python scripts/bench_frames.py [--preset thick] [--width 160 --height 90] [--backend compiled] [--device cpu]
                                   [--frames 13] [--skip 3] [--pt-repeats 10] [--threads 2] [--json out.json]
                                   [--nrc KEY=VALUE ...] [overrides ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from lab import REPO
from lab.render import renderer, stopped_by

VDB = REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb"  # ../shared/data/ from the repo root


class _Fallbacks(logging.Handler):
    """Collects the machine's notes that a step could not be built ahead of time (it then runs torch.compile)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if "ahead-of-time compile of the step failed" in record.getMessage():
            self.lines.append(record.getMessage())


def spread(xs: list[float]) -> dict[str, float]:
    return {"median": statistics.median(xs), "p95": float(np.percentile(xs, 95)), "max": max(xs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="thick", help="the scene type (conf/scene/)")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=90)
    ap.add_argument("--backend", default="compiled", choices=["auto", "eager", "compiled"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=13)
    ap.add_argument("--skip", type=int, default=3)
    ap.add_argument("--pt-repeats", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--vdb", type=Path, default=VDB, help="the Disney cloud (default: ../shared/data/)")
    ap.add_argument("--nrc", action="append", default=[], metavar="KEY=VALUE",
                    help="an override for the NRC renderer only (repeatable), e.g. renderer.training.carry_frames=4")
    ap.add_argument("overrides", nargs="*", help="config overrides for both renderers")
    args = ap.parse_args()
    if args.frames <= args.skip:
        ap.error(f"--frames ({args.frames}) must exceed --skip ({args.skip})")
    torch.set_num_threads(args.threads)
    scene = [f"scene={args.preset}", f"scene.volume.path={args.vdb}", f"scene.camera.width={args.width}",
             f"scene.camera.height={args.height}", "scene.integrator.spp=1", f"device={args.device}",
             f"renderer.backend={args.backend}", *args.overrides]

    fallbacks = _Fallbacks()  # a step that could not be packaged runs JIT code, slower: say so beside the figures
    machine_log = logging.getLogger("nrc.render.wavefront.machine")
    machine_log.addHandler(fallbacks)
    machine_log.setLevel(logging.INFO)

    t0 = time.perf_counter()
    nrc = renderer(["renderer=nrc", *scene, f"frames={args.frames}", "renderer.log.tensorboard=false", *args.nrc],
                   absolute=True)
    result = nrc.render()
    stopped_by(result.metrics, args.frames)
    nrc_process = time.perf_counter() - t0
    h = result.metrics["history"]
    k = slice(args.skip, args.frames)
    calls = h["iterations"][k]
    frames = h["time_frame_s"][k]
    trace = h["time_trace_s"][k]
    events = h["scatter_events"][k]
    out_nrc = {
        "frame_s": spread(frames), **{f"{s}_s": statistics.median(h[f"time_{s}_s"][k]) for s in ("trace", "infer", "train")},
        "train_work_s": statistics.median(h.get("time_train_work_s", h["time_train_s"])[k]),
        "overlap": result.metrics["train_beside_trace"] > 0,
        "calls": statistics.median(calls), "ms_per_call": 1e3 * statistics.median(t / c for t, c in zip(trace, calls)),
        "events": statistics.median(events), "us_per_event": 1e6 * statistics.median(t / e for t, e in zip(trace, events)),
        "startup_s": sum(h.get("time_compile_s", [])), "process_s": nrc_process, "backend": result.metrics["backend"],
        "cuda_graphs": result.metrics.get("cuda_graphs"),
        "unbiased_fraction": result.metrics["unbiased_fraction"], "training_image": result.metrics["training_image"],
        "in_flight": statistics.median(h["training_paths_in_flight"][k]),
        "dropped": sum(h["training_paths_dropped"]),
    }

    t0 = time.perf_counter()
    runs = []
    for r in range(args.pt_repeats + 1):  # the first loads (or builds) the compiled step
        runs.append(renderer(["renderer=pt", *scene, f"scene.integrator.seed={r + 1}"], absolute=True).render().metrics)
    pt_process = time.perf_counter() - t0
    m = runs[1:] if len(runs) > 1 else runs
    out_pt = {
        "frame_s": spread([x["time_render_s"] for x in m]), "calls": statistics.median(x["iterations"] for x in m),
        "ms_per_call": 1e3 * statistics.median(x["time_render_s"] / x["iterations"] for x in m),
        "events": statistics.median(x["scatter_events"] for x in m),
        "us_per_event": 1e6 * statistics.median(x["time_render_s"] / x["scatter_events"] for x in m),
        "tail_calls": statistics.median(x.get("tail_calls", 0) for x in m),
        "startup_s": runs[0]["time_compile_s"], "process_s": pt_process, "backend": runs[0]["backend"],
        "cuda_graphs": runs[-1].get("cuda_graphs"),
    }
    out = {"scene": args.preset, "size": [args.width, args.height], "device": args.device, "threads": args.threads,
           "nrc": out_nrc, "pt": out_pt, "ratio_frame": out_nrc["frame_s"]["median"] / out_pt["frame_s"]["median"],
           "ratio_per_event": out_nrc["us_per_event"] / out_pt["us_per_event"], "step_fallbacks": fallbacks.lines}
    for name, o in (("nrc", out_nrc), ("pt 1 spp", out_pt)):
        f = o["frame_s"]
        extra = (f", trace {o['trace_s']:.3f} / infer {o['infer_s']:.3f} / train {o['train_s']:.3f} s (steps "
                 f"{o['train_work_s']:.3f} s{', beside the next trace' if o['overlap'] else ''})"
                 if "trace_s" in o else f", {o['tail_calls']:.0f} tail calls")
        print(f"{name:8s} frame {f['median']:.3f} s (p95 {f['p95']:.3f}, max {f['max']:.3f}){extra}; {o['calls']:.0f} "
              f"calls, {o['ms_per_call']:.3f} ms a call; {o['events']:.0f} events, {o['us_per_event']:.2f} us an event; "
              f"start-up {o['startup_s']:.1f} s, process {o['process_s']:.1f} s ({o['backend']})")
    print(f"NRC frame / pt 1-spp frame {out['ratio_frame']:.2f}x; per event {out['ratio_per_event']:.2f}x")
    for line in fallbacks.lines:
        print(f"WARNING: not the packaged step, so not the figures of a packaged one: {line}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
