"""Does a Hydra sweep recompile? Start-up per sweep point, basic launcher (one process) and joblib (several).

1. Basic launcher, one process, ``renderer.backend=compiled``, an empty inductor cache: a sweep over density
   scale, g, albedo, camera position and a second VDB file (``tests/data/scattered_zip.vdb``). The step compiles
   for the first point only: every point's ``metrics.json`` reports ``compiled_graphs_in_process`` (Dynamo's
   count; constant when nothing recompiles) and ``time_compile_s``.
2. Joblib launcher (two worker processes, one thread each) over the same cache, twice: the C++ kernels are
   specialised on the thread count, so the first joblib sweep compiles a 1-thread entry in each worker (in
   parallel) and the second loads it; the start-up of each point is reported.

    python scripts/bench_sweep.py [--spp 4] [--json out.json]
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


def sweep(args: list[str], env: dict[str, str], out: Path) -> tuple[float, list[dict]]:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "nrc", "-m", *args, f"hydra.sweep.dir={out}"], cwd=REPO, env=env,
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        sys.exit(f"bench_sweep: sweep failed:\n{p.stderr[-3000:]}")
    rows = []
    for m in sorted(out.glob("*/metrics.json"), key=lambda f: int(f.parent.name)):
        d = json.loads(m.read_text())
        rows.append({"job": int(m.parent.name), "backend": d["backend"], "compile_s": d.get("time_compile_s"),
                     "graphs": d.get("compiled_graphs_in_process"), "render_s": d["time_render_s"],
                     "cache_hit": d.get("compile_cache_hit")})
    return wall, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    cache = tempfile.mkdtemp(prefix="nrc-sweep-inductor-")
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
    vdb = REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb"
    second = REPO / "tests" / "data" / "scattered_zip.vdb"
    common = ["+experiment=bench_canonical", f"scene.integrator.spp={args.spp}", "renderer.backend=compiled",
              f"scene.volume.path={vdb},{second}", "scene.volume.density_scale=0.3,0.6", "scene.volume.g=0.5,0.9"]
    result = {}
    with tempfile.TemporaryDirectory() as d:
        wall, rows = sweep([*common, "scene.volume.albedo=0.8,1.0", "scene.camera.position=[64,0,0],[0,10,70]"],
                           env, Path(d) / "basic")
        result["basic"] = {"wall_s": wall, "jobs": rows}
        graphs = {r["graphs"] for r in rows}
        print(f"basic launcher: {len(rows)} points in one process, {wall:.1f} s; compiled graphs in the process: "
              f"{sorted(graphs)} (constant = nothing recompiled); start-up of point 0: {rows[0]['compile_s']:.1f} s, "
              f"of the others: max {max(r['compile_s'] for r in rows[1:]):.2f} s")
        if len(graphs) != 1:
            print("bench_sweep: the sweep recompiled")
        for run in ("joblib_first", "joblib_second"):
            wall, rows = sweep([*common, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"], env, Path(d) / run)
            result[run] = {"wall_s": wall, "jobs": rows}
            starts = ", ".join(f"{r['compile_s']:.1f}" for r in rows)
            print(f"{run} (2 worker processes of 1 thread each): {len(rows)} points, {wall:.1f} s; start-up per point "
                  f"(s, 0 = the worker had it): {starts}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
