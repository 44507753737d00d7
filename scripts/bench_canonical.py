"""Whole-process timing of the canonical benchmark (``conf/experiment/bench_canonical.yaml``) against Mitsuba 3.

Runs, one after the other in the same minutes, each as its own process (start-up, scene load and compilation
count, as a user waits for them):

1. ``python -m nrc +experiment=bench_canonical`` with the default backend and an empty inductor cache (a
   first run), then the same command again (second run: the cache is warm), and with
   ``renderer.backend=eager`` / ``compiled``;
2. Mitsuba 3 ``scalar_rgb`` and ``llvm_ad_rgb`` (when LLVM is installed) rendering the same scene through
   :mod:`nrc.evaluation.mitsuba_bridge` in a fresh process.

Prints the wall times, the render times from ``metrics.json`` and the ratios; ``--json`` writes them.

    python scripts/bench_canonical.py [--repeats 1] [--threads 2] [--spp 512] [--json out.json] [overrides...]

Hydra overrides after the options change the scene on both sides, e.g. the thick medium of ``scene=thick``::

    python scripts/bench_canonical.py --spp 64 scene.volume.density_scale=5 scene.volume.albedo=0.99 \
        scene.volume.g=0.85 scene.integrator.max_scatter=1024
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lab import REPO

MITSUBA = r"""
import sys, time
t0 = time.perf_counter()
from nrc.config import compose
from nrc.evaluation.mitsuba_bridge import render_mitsuba
from nrc.scene import load_scene
cfg = compose(["+experiment=bench_canonical", f"scene.integrator.spp={sys.argv[4]}", "scene.volume.path=" + sys.argv[3],
               *sys.argv[6:]])
img, secs = render_mitsuba(load_scene(cfg.scene), threads=int(sys.argv[5]), variant=sys.argv[2])
print(f"RENDER {secs} MEAN {float(img.mean())}")
"""


def run(cmd: list[str], env: dict[str, str]) -> tuple[float, str]:
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        sys.exit(f"bench_canonical: {' '.join(cmd)} failed:\n{p.stderr[-2000:]}")
    return wall, p.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--skip-mitsuba", action="store_true")
    ap.add_argument("--json", type=Path)
    args, overrides = ap.parse_known_args()
    vdb = str(REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb")
    cache = tempfile.mkdtemp(prefix="nrc-inductor-")
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache, "OMP_NUM_THREADS": str(args.threads)}
    out: dict[str, list] = {}

    def nrc(label: str, extra: list[str]) -> None:
        for _ in range(args.repeats if label != "auto_first" else 1):
            with tempfile.TemporaryDirectory() as d:
                wall, _ = run([sys.executable, "-m", "nrc", "+experiment=bench_canonical", f"scene.integrator.spp={args.spp}",
                               f"hydra.run.dir={d}", *overrides, *extra], env)
                m = json.loads((Path(d) / "metrics.json").read_text())
            row = {"wall_s": wall, "render_s": m["time_render_s"], "compile_s": m.get("time_compile_s"),
                   "backend": m["backend"], "reason": m.get("backend_reason"), "image_mean": None}
            out.setdefault(label, []).append(row)
            print(f"nrc {label:12s} wall {wall:6.1f} s  render {row['render_s']:6.2f} s  start-up (compile/load) "
                  f"{row['compile_s'] or 0:5.1f} s  backend {row['backend']}" + (f" ({row['reason']})" if row["reason"] else ""),
                  flush=True)

    nrc("auto_first", [])
    nrc("auto_second", [])
    nrc("eager", ["renderer.backend=eager"])
    nrc("compiled", ["renderer.backend=compiled"])
    if not args.skip_mitsuba:
        for variant in ("scalar_rgb", "llvm_ad_rgb"):
            for _ in range(args.repeats):
                try:
                    wall, stdout = run([sys.executable, "-c", MITSUBA, str(REPO / "conf"), variant, vdb, str(args.spp),
                                        str(args.threads), *overrides], env)
                except SystemExit as exc:
                    print(f"mitsuba {variant}: failed ({str(exc).splitlines()[-1][:200]})")
                    break
                render = float(stdout.split("RENDER")[1].split()[0])
                out.setdefault(variant, []).append({"wall_s": wall, "render_s": render})
                print(f"mitsuba {variant:11s} wall {wall:6.1f} s  render {render:6.2f} s", flush=True)
    samples = 128 * 72 * args.spp
    best = {k: min(r["wall_s"] for r in v) for k, v in out.items()}
    best_render = {k: min(r["render_s"] for r in v) for k, v in out.items()}
    for ref in ("scalar_rgb", "llvm_ad_rgb"):
        if ref in best:
            for k in ("auto_first", "auto_second", "eager", "compiled"):
                print(f"whole process {k} vs mitsuba {ref}: {best[ref] / best[k]:.2f}x; "
                      f"render alone: {best_render[ref] / best_render[k]:.2f}x")
    print(f"samples {samples}; render samples/s: " + ", ".join(f"{k} {samples / v:,.0f}" for k, v in best_render.items()))
    if args.json:
        args.json.write_text(json.dumps({"samples": samples, "threads": args.threads, "overrides": overrides,
                                         "runs": out}, indent=2))


if __name__ == "__main__":
    main()
