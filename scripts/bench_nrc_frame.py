"""Time NRC frames (trace / infer / train) on a side-lit Disney-cloud scene, per backend.

Renders ``--frames`` frames of ``renderer=nrc`` (today's defaults: 1 spp, 128x128 training paths) at
``--width``x``--height`` and prints the median per-frame stage times of the frames after ``--skip`` warm-up
frames, with the process's start-up (compile or cache load) reported apart. Not a test: speed lives here and
in docs/measurements/speed.md.

    python scripts/bench_nrc_frame.py [--backend eager|compiled|auto] [--frames 12] [--threads 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from lab import REPO
from lab.render import renderer as nrc_renderer
from lab.render import stopped_by

VDB = REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb"  # ../shared/data/ from the repo root


def side_lit(vdb: Path) -> list[str]:
    return ["scene=sun_front", "scene.volume.source=vdb", f"scene.volume.path={vdb}", "scene.volume.density_scale=0.6",
            "scene.lights.0.direction=[-1.0,-0.25,0.0]", "scene.lights.0.irradiance=[3.0,3.0,3.0]"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="auto", choices=["auto", "eager", "compiled"])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--skip", type=int, default=2)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=90)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--vdb", type=Path, default=VDB, help="the Disney cloud (default: ../shared/data/)")
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. device=cuda")
    args = ap.parse_args()
    if args.frames <= args.skip:
        ap.error(f"--frames ({args.frames}) must exceed --skip ({args.skip}): the medians are over the frames after it")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    renderer = nrc_renderer(["renderer=nrc", *side_lit(args.vdb), f"scene.camera.width={args.width}",
                             f"scene.camera.height={args.height}", f"frames={args.frames}",
                             f"renderer.backend={args.backend}", "renderer.log.tensorboard=false", *args.overrides])
    result = renderer.render()
    stopped_by(result.metrics, args.frames)
    total = time.perf_counter() - t0
    h = result.metrics["history"]
    stages = {k: statistics.median(h[f"time_{k}_s"][args.skip:]) for k in ("trace", "infer", "train", "frame")}
    startup = sum(h.get("time_compile_s", []))
    out = {"device": str(renderer.device), "backend": result.metrics["backend"], "backend_reason": result.metrics["backend_reason"],
           "threads": args.threads, "size": [args.width, args.height], "frames": args.frames,
           "median_s": stages, "startup_s": startup, "process_s": total,
           "image_mean": float(result.image.mean())}
    print(f"nrc frame ({out['backend']}, {args.width}x{args.height}, {args.threads} threads): "
          + ", ".join(f"{k} {v:.3f} s" for k, v in stages.items())
          + f"; start-up {startup:.1f} s; whole process {total:.1f} s")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
