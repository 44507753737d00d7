"""Where NRC pays off: speed versus error over optical depth (the crossover map).

For every point -- the thick preset (``scene=thick``: the Disney cloud, albedo 0.99, g 0.85, sun + sky) at density
scale 0.35, 0.6, 2, 5 and 10, and at albedo 0.95 and 1.0 at density 5 -- it runs ``scripts/speed_vs_error.py``
(single frames, equal time per frame, OIDN on both sides; its reference rendered and kept in data/references when
missing) and collects, from its ``summary.json``: the median optical depth over the camera rays that see the medium
(``nrc.volume.optical_depth``), NRC / PT and NRC+OIDN / PT+OIDN at equal time per frame (floor-corrected relMSE
over the medium pixels), NRC's image mean over the reference's, and the flicker of each. Writes
``<out>/map.json``, ``<out>/map.md`` and ``<out>/map.png`` (NRC+OIDN / PT+OIDN against optical depth, a line per
albedo). Each point's own tables stay in ``<out>/<point>/``. A point whose ``summary.json`` exists is not run again
(delete it to re-measure). Usage::

    python scripts/crossover_map.py --out docs/results/crossover_160x90 [--points d0.6,d5] [--width 160 --height 90]
    python scripts/crossover_map.py --out docs/results/crossover_160x90_cold --cold-start 30

**Cold start** (``--cold-start FRAMES``): instead of single frames at equal time per frame, a static camera from an
empty cache: NRC's running mean after FRAMES frames against the path tracer's running mean (``--cold-pt-spp``-spp
frames) at the same wall time, start-up (imports, scene, the step's load) counted on both sides, OIDN on both.

**Points as jobs** (``--jobs local|slurm``, submitit, ``pip install -e '.[cluster]'``): each missing point runs as
its own job, which holds the point's path tracer and NRC runs (equal-time ratios are valid only when both are timed
on one machine with nothing else running): ``local`` runs them one after another on this machine, ``slurm`` submits
one job per point on a node of its own (``--exclusive``; ``--slurm partition=cpu --slurm cpus_per_task=32
--slurm timeout_min=120``). Each summary records its node, machine type and threads; the map is built from the
summaries once every job is done, and refuses to mix machine types. The references are rendered first
(``python -m nrc.reference_app``, docs/running.md): a job never renders one.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from lab import REPO
from lab.jobs import check_one_machine_type, run_commands
from lab.points import POINTS, optical_depth, point_scene, require_references


def pick(summary: dict, config: str, baseline: str, cold: bool = False) -> dict | None:
    """The equal-time entry of ``config`` against ``baseline`` with the lowest floor-corrected ratio (over NRC's
    spp per frame); ``cold``: the accumulated entry at NRC's last frame (equal wall time, start-up included)."""
    mode = "accumulate" if cold else "single"
    qs = [q for q in summary.get("equal_time", []) if q["config"] == config and q.get("baseline") == baseline
          and q.get("mode", "single") == mode]
    if cold:
        return max(qs, key=lambda q: q["frames"]) if qs else None
    key = lambda q: q.get("ratio_rel_mse_medium_corr") if q.get("ratio_rel_mse_medium_corr") is not None \
        else float("inf")  # noqa: E731
    return min(qs, key=key) if qs else None


def run_jobs(todo: dict[str, list[str]], scenes: dict[str, tuple[list[str], int]], args: argparse.Namespace) -> None:
    """Each point of ``todo`` as a submitit job (see the module docstring); returns when all are done."""
    require_references(scenes, "crossover_map")
    run_commands(todo, args.jobs, args.out / ".jobs", REPO, args.slurm)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--points", default=",".join(POINTS))
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=90)
    p.add_argument("--pt-spp", default="1,2,4,8,16")
    p.add_argument("--warmup", type=int, default=30)
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--nrc-spp", default="1,4", help="NRC spp per frame (the best at equal time is reported)")
    p.add_argument("--nrc-repeats", type=int, default=1,
                   help="independent NRC runs (seeds) per point, their scored frames pooled: one seed is one draw of "
                        "a spread as wide as some differences the map reports")
    p.add_argument("--ref-spp", type=int, default=None,
                   help="spp of every point's reference (default: each point's own, POINTS); larger images need fewer")
    p.add_argument("--nrc", default="renderer=nrc,renderer.backend=compiled", help="the NRC configuration's overrides")
    p.add_argument("--pt", default="renderer=pt,renderer.backend=compiled,transmittance=ratio",
                   help="the path tracer configuration's overrides")
    p.add_argument("--cold-start", type=int, default=0, metavar="FRAMES",
                   help="instead of single frames: the cold start at equal wall time, NRC's running mean after FRAMES "
                        "frames from an empty cache against the path tracer's at the same time, start-up included")
    p.add_argument("--cold-pt-spp", type=int, default=16, help="spp of each accumulated path-traced frame (cold start)")
    p.add_argument("--cold-budget-s", type=float, default=60.0,
                   help="seconds of rendering per configuration (cold start): the path tracer must outlast NRC")
    p.add_argument("--jobs", choices=["none", "local", "slurm"], default="none",
                   help="run each missing point as its own job (submitit): local, one at a time; slurm, a node each")
    p.add_argument("--slurm", action="append", default=[], metavar="KEY=VALUE",
                   help="a Slurm parameter of the jobs (partition=cpu, cpus_per_task=32, timeout_min=120, ...)")
    args, extra = p.parse_known_args(argv)
    args.out = args.out.resolve()
    os.chdir(REPO)
    args.out.mkdir(parents=True, exist_ok=True)
    points = {}
    for name in args.points.split(","):
        scene, ref_spp = point_scene(name, args.width, args.height, "crossover_map")
        ref_spp = args.ref_spp or ref_spp
        scene = [*scene, *extra]
        out = args.out / name
        cmd = [sys.executable, str(REPO / "scripts" / "speed_vs_error.py"), "--denoise", "--configs", "", "--preset",
               "none", "--config", f"pt_compiled={args.pt}", "--config", f"nrc={args.nrc}",
               "--ref-spp", str(ref_spp), "--out", os.path.relpath(out, REPO), "--quiet"]
        if args.cold_start:  # accumulated, static camera, start-up counted on both sides
            cmd += ["--mode", "accumulate", "--acc-startup", "--acc-nrc-last", "--acc-configs", "all", "--acc-repeats", "1",
                    "--acc-nrc-frames", str(args.cold_start), "--acc-max-frames", "4096",
                    "--acc-budget-s", str(args.cold_budget_s), "--acc-pt-spp", str(args.cold_pt_spp), *scene]
        else:
            cmd += ["--mode", "single", "--repeats", "2", "--pt-spp", args.pt_spp, "--warmup", str(args.warmup),
                    "--frames", str(args.frames), "--nrc-spp", args.nrc_spp, "--nrc-repeats", str(args.nrc_repeats),
                    *scene]
        points[name] = (scene, ref_spp, out, cmd)
    todo = {name: cmd for name, (_, _, out, cmd) in points.items() if not (out / "summary.json").is_file()}
    if args.jobs != "none" and todo:
        run_jobs(todo, {name: points[name][:2] for name in todo}, args)
    for name, cmd in todo.items():
        if args.jobs == "none":
            t0 = time.perf_counter()
            print(f"[{name}] {' '.join(cmd[2:])}", flush=True)
            subprocess.run(cmd, cwd=REPO, check=True)
            print(f"[{name}] done in {time.perf_counter() - t0:.0f} s", flush=True)
    summaries = {name: json.loads((out / "summary.json").read_text()) for name, (_, _, out, _) in points.items()}
    check_one_machine_type(summaries, "crossover_map")
    results = []
    for name, (scene, ref_spp, out, _) in points.items():
        s = summaries[name]
        res = {"point": name, "node": s["meta"].get("node"), "machine_type": s["meta"].get("machine_type"), **optical_depth(scene), "ref_spp": ref_spp,
               "rel_mse_floor_medium": s["meta"]["rel_mse_floor_medium"]}
        pairs = [("raw", "nrc", "pt"), ("oidn", "nrc+oidn", "pt+oidn")]
        if args.cold_start:  # NRC's last frame alone beside its running mean
            pairs += [("raw_last", "nrc:last", "pt"), ("oidn_last", "nrc:last+oidn", "pt+oidn")]
        for key, cfg, base in pairs:
            q = pick(s, cfg, base, bool(args.cold_start))
            res[f"ratio_{key}"] = None if q is None else q.get("ratio_rel_mse_medium_corr")
            res[f"ratio_{key}_uncorrected"] = None if q is None else q.get("ratio_rel_mse_medium")
            res[f"pt_extrapolated_{key}"] = None if q is None else q.get("extrapolated")
            res[f"time_frame_{key}_s"] = None if q is None else q.get("time_s")
            res[f"nrc_spp_{key}"] = None if q is None else q.get("spp")
        for cfg in ("nrc", "nrc+oidn", "pt_compiled", "pt_compiled+oidn", "nrc:last", "nrc:last+oidn"):
            rows = [r for r in s["rows"] if r["config"] == cfg]
            if cfg.startswith("nrc") and res.get("nrc_spp_oidn") is not None:  # NRC at its best spp per frame
                rows = [r for r in rows if r["spp"] == res["nrc_spp_oidn"]] or rows
            if not rows:
                continue
            if args.cold_start:  # NRC at its last frame, PT's running mean nearest NRC's time
                t = res["time_frame_oidn_s"] or 0.0
                fastest = max(rows, key=lambda r: r["frames"]) if cfg.startswith("nrc") else \
                    min(rows, key=lambda r: abs(r["time_s"] - t))
                res[f"{cfg}_frames"] = fastest["frames"]
            else:
                fastest = min(rows, key=lambda r: r["time_s"])
            res[f"{cfg}_mean_ratio_medium"] = fastest.get("mean_ratio_medium")
            res[f"{cfg}_rel_mse_medium"] = fastest.get("rel_mse_medium")
            res[f"{cfg}_flicker_medium"] = fastest.get("flicker_medium")
            res[f"{cfg}_time_s"] = fastest["time_s"]
        results.append(res)
        print(json.dumps(res), flush=True)
    (args.out / "map.json").write_text(json.dumps({"argv": sys.argv[1:], "points": results}, indent=2))
    if args.cold_start:
        lines = [f"{args.width} x {args.height}, **cold start at equal wall time**: NRC's running mean after "
                 f"{args.cold_start} frames from an empty cache (a static camera) against the compiled path tracer's "
                 f"running mean of {args.cold_pt_spp}-spp frames at the same time, start-up included on both sides "
                 "(imports, scene, the warm-up frame: the step's load from the compile cache); OIDN on both sides "
                 "for the +OIDN column, its time included; ratios of floor-corrected relMSE over the medium pixels "
                 "(< 1: NRC better); PT interpolated log-log between its running means (slope -1 beyond them).", "",
                 f"Two NRC images: its running mean over the {args.cold_start} frames (a static camera's "
                 f"accumulation, which keeps the untrained cache's first frames) and its last frame alone.", "",
                 "| point | median tau | albedo | NRC / PT: mean, frame | NRC+OIDN / PT+OIDN: mean, frame | "
                 "NRC whole time (s) | PT frames by then | NRC image mean / ref: mean, frame | ref floor |",
                 "|---|---:|---:|---|---|---:|---:|---|---:|"]
    else:
        lines = [f"{args.width} x {args.height}, equal time per frame after {args.warmup} NRC warm-up frames; ratios "
                 "of floor-corrected relMSE over the medium pixels (< 1: NRC better); PT = the compiled path tracer at "
                 "1-16 spp (when NRC's frame is faster than PT's 1-spp frame, PT's 1-spp error is used: in PT's "
                 "favour); fastest-frame rows for the image mean and flicker.", "",
                 "| point | median tau | albedo | NRC / PT | NRC+OIDN / PT+OIDN (NRC spp) | NRC frame (s) | PT 1 spp "
                 "(s) | NRC mean / ref | flicker NRC / NRC+OIDN / PT / PT+OIDN | ref floor |",
                 "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|"]

    def f(x, n=3):
        return "–" if x is None else f"{x:.{n}g}"

    for r in sorted(results, key=lambda r: (r["albedo"], r["tau_median"])):
        if args.cold_start:
            lines.append(f"| {r['point']} | {r['tau_median']:.1f} | {r['albedo']:g} | {f(r['ratio_raw'])}, "
                         f"{f(r.get('ratio_raw_last'))} | {f(r['ratio_oidn'])}, {f(r.get('ratio_oidn_last'))} | "
                         f"{f(r.get('time_frame_oidn_s'))} | {r.get('pt_compiled+oidn_frames')} | "
                         f"{f(r.get('nrc_mean_ratio_medium'))}, {f(r.get('nrc:last_mean_ratio_medium'))} | "
                         f"{f(r['rel_mse_floor_medium'], 2)} |")
            continue
        lines.append(f"| {r['point']} | {r['tau_median']:.1f} | {r['albedo']:g} | {f(r['ratio_raw'])} | "
                     f"{f(r['ratio_oidn'])} ({r.get('nrc_spp_oidn')}) | {f(r.get('time_frame_oidn_s'))} | {f(r.get('pt_compiled_time_s'))} | "
                     f"{f(r.get('nrc_mean_ratio_medium'))} | {f(r.get('nrc_flicker_medium'), 2)} / "
                     f"{f(r.get('nrc+oidn_flicker_medium'), 2)} / {f(r.get('pt_compiled_flicker_medium'), 2)} / "
                     f"{f(r.get('pt_compiled+oidn_flicker_medium'), 2)} | {f(r['rel_mse_floor_medium'], 2)} |")
    (args.out / "map.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        for albedo in sorted({r["albedo"] for r in results}):
            pts = sorted((r["tau_median"], r["ratio_oidn"]) for r in results
                         if r["albedo"] == albedo and r["ratio_oidn"] is not None and r["ratio_oidn"] > 0)
            if pts:
                ax.loglog(*zip(*pts), "-o", label=f"albedo {albedo:g}, NRC+OIDN / PT+OIDN"
                          + (" (NRC's running mean)" if args.cold_start else ""))
            pts = sorted((r["tau_median"], r["ratio_oidn_last"]) for r in results if r["albedo"] == albedo
                         and r.get("ratio_oidn_last") is not None and r["ratio_oidn_last"] > 0)
            if pts:
                ax.loglog(*zip(*pts), "--^", label=f"albedo {albedo:g}, NRC+OIDN / PT+OIDN (NRC's last frame)")
        pts = sorted((r["tau_median"], r["ratio_raw"]) for r in results if r["ratio_raw"] and r["ratio_raw"] > 0)
        if pts:
            ax.loglog(*zip(*pts), ":s", color="grey", label="raw NRC / raw PT (all albedos)")
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_xlabel("median optical depth of the camera rays that see the medium")
        ax.set_ylabel("relMSE ratio at equal wall time (cold start)" if args.cold_start
                      else "relMSE ratio at equal time per frame")
        ax.set_title(f"Where NRC pays off ({args.width} x {args.height}); below 1: NRC wins")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.out / "map.png", dpi=110)
    except ImportError:
        pass
    print((args.out / "map.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
