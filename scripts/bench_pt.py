"""Benchmark the path tracer against Mitsuba 3 on the canonical scene (samples per second, same run).

Scene: the ``sun`` preset with the shared Disney cloud (``../shared/data/wdas_cloud_sixteenth.vdb``),
``density_scale 0.6``, ``g 0.8``, ``max_scatter 64``, no Russian roulette, 128 x 72 pixels. Start-up
(scene load, first-call warm-up) is excluded from the timings. When Mitsuba 3 is installed
(``pip install mitsuba==3.9.1``) the same scene is rendered with its ``scalar_rgb`` ``volpath``
(``max_depth = max_scatter + 1``, no roulette) in the same run and the ratio is printed, with the
relative difference of the two image means as an agreement check.

``--backend compiled`` times the ``torch.compile``'d state machine (``renderer.backend``): its start-up
(compilation, or loading it from the inductor cache under ``$TORCHINDUCTOR_CACHE_DIR``, default
``~/.cache/nrc/inductor``) is reported apart and excluded from samples/s, like the eager warm-up.

Usage::

    python scripts/bench_pt.py [--spp 64] [--backend eager|compiled] [--vdb PATH] [--free-flight brick|global]
        [--transmittance ratio] [--slots N] [--steps-per-call K] [--repeats R]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from lab import REPO
from lab.render import setup

DEFAULT_VDB = REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb"


def config(args: argparse.Namespace, spp: int, width: int, height: int):
    """The benchmark's composed config and its loaded scene (:func:`lab.render.setup`)."""
    return setup([
        "renderer=pt", "scene=sun_front", "scene.volume.source=vdb", f"scene.volume.path={args.vdb}",
        "scene.volume.density_scale=0.6", "scene.volume.g=0.8", "scene.integrator.max_scatter=64",
        f"scene.integrator.spp={spp}", f"scene.camera.width={width}", f"scene.camera.height={height}",
        f"renderer.free_flight={args.free_flight}", f"transmittance={args.transmittance}",
        "renderer.russian_roulette.enabled=false", f"renderer.backend={args.backend}",
        f"renderer.slots={args.slots}", f"renderer.steps_per_call={args.steps_per_call}", f"renderer.brick={args.brick}",
    ])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=72)
    ap.add_argument("--vdb", type=Path, default=DEFAULT_VDB)
    ap.add_argument("--backend", default="eager", choices=["eager", "compiled"])
    ap.add_argument("--slots", type=int, default=1 << 16)
    ap.add_argument("--steps-per-call", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=1, help="timed renders of each renderer (best and range printed)")
    ap.add_argument("--free-flight", default="brick", choices=["brick", "global"])
    ap.add_argument("--brick", default="auto", help="majorant brick edge in voxels, or auto")
    ap.add_argument("--transmittance", default="ratio")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()
    if not args.vdb.is_file():
        sys.exit(f"bench_pt: Disney cloud not found at {args.vdb} (pass --vdb)")
    torch.set_num_threads(args.threads)

    # Warm-up on a tiny image (first-call costs, allocator), then the timed render.
    t_warm = time.perf_counter()  # the warm-up in all: its scene's load, renderer and render
    warm = config(args, 1, 16, 9)
    warm_metrics = warm.renderer().render().metrics
    t_warm = time.perf_counter() - t_warm
    bench = config(args, args.spp, args.width, args.height)
    scene = bench.scene
    t0 = time.perf_counter()
    pt = bench.renderer()
    times, result = [], None
    for _ in range(args.repeats):
        result = pt.render(progress=args.repeats == 1)
        if result.metrics["backend"] != args.backend:
            sys.exit(f"bench_pt: fell back to {result.metrics['backend']}: {result.metrics['backend_reason']}")
        times.append(result.metrics["time_render_s"])  # excludes the compiled backend's start-up
    startup = warm_metrics.get("time_compile_s", 0.0)  # this process's first compile (or inductor cache load)
    elapsed = min(times)
    samples = args.width * args.height * args.spp
    m = result.metrics
    out = {
        "scene": "sun, wdas_cloud_sixteenth, density_scale 0.6, g 0.8, max_scatter 64, no RR",
        "resolution": [args.width, args.height], "spp": args.spp, "threads": args.threads,
        "backend": args.backend, "slots": args.slots, "steps_per_call": args.steps_per_call,
        "free_flight": m["free_flight"], "transmittance": args.transmittance, "torch": torch.__version__,
        "nrc_startup_seconds": startup, "nrc_seconds": times, "nrc_samples_per_s": [samples / t for t in times],
        "nrc_image_mean": float(result.image.mean()),
        "nrc_stage_seconds": {k: v for k, v in m.items() if k.startswith("time_")},
        "nrc_counts": {k: m[k] for k in ("tracking_steps", "shadow_steps", "shadow_rays", "slot_steps") if k in m},
    }
    if args.backend == "compiled":
        print(f"nrc start-up in this process (compile, or load from the inductor cache): {startup:.1f} s "
              f"(warm-up render {t_warm:.1f} s in all; re-tracing for the timed scene "
              f"{time.perf_counter() - t0 - sum(times):.1f} s)")
    rates = ", ".join(f"{samples / t:,.0f}" for t in times)
    print(f"nrc pt ({args.backend}): {samples} samples, best {elapsed:.2f} s = {samples / elapsed:,.0f} samples/s "
          f"(runs: {rates})")
    per = {k: v / samples for k, v in out["nrc_counts"].items()}
    print("nrc per camera sample: " + ", ".join(f"{k} {v:.2f}" for k, v in per.items())
          + "; stage seconds: " + ", ".join(f"{k[5:-2]} {v:.2f}" for k, v in out["nrc_stage_seconds"].items()
                                              if k not in ("time_render_s", "time_compile_s")))

    if not args.no_mitsuba:
        from nrc.evaluation.mitsuba_bridge import mitsuba_available, render_mitsuba

        if mitsuba_available():
            render_mitsuba(warm.scene, threads=args.threads)  # warm-up
            mtimes = []
            for _ in range(args.repeats):
                img, secs = render_mitsuba(scene, threads=args.threads)
                mtimes.append(secs)
            secs = min(mtimes)
            out.update({
                "mitsuba_seconds": mtimes, "mitsuba_samples_per_s": [samples / t for t in mtimes],
                "mitsuba_image_mean": float(np.mean(img)), "ratio_nrc_over_mitsuba": secs / elapsed,
                "image_mean_rel_diff": float(result.image.mean() / np.mean(img) - 1.0),
            })
            rates = ", ".join(f"{samples / t:,.0f}" for t in mtimes)
            print(f"mitsuba:  {samples} samples, best {secs:.2f} s = {samples / secs:,.0f} samples/s (runs: {rates})")
            print(f"ratio nrc/mitsuba (best samples/s each): {secs / elapsed:.2f}; "
                  f"image means differ by {out['image_mean_rel_diff'] * 100:+.2f} %")
        else:
            print("mitsuba: not installed (pip install mitsuba==3.9.1); skipped")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
