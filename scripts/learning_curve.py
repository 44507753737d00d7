"""How fast NRC learns: its error frame by frame from an untrained cache, against the path tracer at equal time.

For each point (``lab.points.POINTS``: the thick preset at a density scale and albedo) and each of ``--seeds`` runs
from an untrained cache (``scene.integrator.seed`` apart): NRC's and NRC+OIDN's relMSE (floor-corrected: the
reference's ``rel_mse_floor_medium`` subtracted) and image mean over the reference's, over the medium pixels, at every
``--every``-th frame, their mean over the seeds with a 95 % interval (mean +- t-quantile x standard error); beside
them the path tracer + OIDN at equal time per frame: its relMSE on the Pareto front of its ``--pt-spp`` frames
(``--pt-repeats`` seeds each, :func:`lab.analysis.baseline_error`) at NRC's frame time (the median over the seeds'
frames after the first), OIDN's time added on both sides; and the crossing frame, the first scored frame from which
NRC+OIDN's mean relMSE stays at or below PT+OIDN's. Writes ``<out>/<point>/curve.{json,md,png}`` and
``<out>/summary.md`` (a row per point in ``<out>``). A point whose ``curve.json`` exists is not run again
(``--force``). Usage::

    python scripts/learning_curve.py --points d2,d5 [--seeds 5 --frames 30 --every 1 --width 160 --height 90]
    python scripts/learning_curve.py --points d5 --label density extra_inputs=density   # an NRC variant

Hydra overrides after the options apply to NRC only (candidates compared on one path tracer); ``--label`` names
the variant's folder (default out: ``docs/results/learning_<W>x<H>/<label>``). ``--backend`` (or a
``renderer.backend=...`` override) sets the backend of both sides (default: what the app chooses; the one used is
reported). ``--jobs local|slurm``: each missing point as its own submitit job (:mod:`lab.jobs`; references rendered
here first, or, for ``slurm``, required to exist).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lab import REPO, repo_relative
from lab.analysis import baseline_error, ci95
from lab.jobs import run_commands, without_jobs
from lab.machine import machine
from lab.points import POINTS, point_scene, require_references
from lab.tables import fmt, pm

TINY = 1e-12  # floor-corrected errors below the floor's resolution (<= 0) are clipped here for log-log reads
KEYS = ("rel_mse", "rel_mse_oidn", "mean_ratio", "mean_ratio_oidn")


# ---------------------------------------------------------------------------- the pure parts
def crossing_frame(frames: list[int], nrc: list[float], pt: float | None) -> int | None:
    """The first of ``frames`` from which ``nrc`` (its error there) stays <= ``pt``; None when it never does."""
    cross = None
    for f, e in zip(frames, nrc):
        if pt is None or e is None or not e <= pt:
            cross = None
        elif cross is None:
            cross = f
    return cross


def scored_frames(frames: int, every: int) -> list[int]:
    """The frames scored (from 1): the first, every ``every``-th and the last."""
    return sorted({1, frames} | set(range(every, frames + 1, every)))


def curve_rows(frames: list[int], per_seed: list[list[dict]], pt_oidn: float | None) -> list[dict]:
    """A row per scored frame: the mean over the seeds of each of :data:`KEYS` and its 95 % half-width (``_ci``),
    PT+OIDN's relMSE at equal time and NRC+OIDN's over it. ``per_seed[s][i]``: seed ``s``'s scores at ``frames[i]``."""
    rows = []
    for i, f in enumerate(frames):
        row: dict[str, Any] = {"frame": f}
        for k in KEYS:
            row[k], row[k + "_ci"] = ci95([seed[i][k] for seed in per_seed])
        row["pt_oidn_rel_mse"] = pt_oidn
        row["ratio_oidn"] = row["rel_mse_oidn"] / pt_oidn if pt_oidn else None
        rows.append(row)
    return rows


def at_frame(rows: list[dict], frame: int, key: str) -> Any:
    return next((r[key] for r in rows if r["frame"] == frame), None)


def markdown(res: dict) -> str:
    s, pt = res["settings"], res["pt_oidn"]
    lines = [f"**{res['point']}** ({s['width']} x {s['height']}, variant `{s['label']}`, NRC overrides "
             f"`{' '.join(s['nrc_overrides']) or 'none'}`): {s['seeds']} NRC runs of {s['frames']} frames from an "
             f"untrained cache, {s['nrc_spp']} spp; backend NRC {res['backend']['nrc']}, PT {res['backend']['pt']}. "
             f"Reference: {res['reference']['path']} ({res['reference']['spp']} spp, noise floor "
             f"{fmt(res['reference']['rel_mse_floor_medium'])} over the medium, subtracted from every relMSE). "
             f"Machine: {res['machine']}.", "",
             f"NRC frame: {fmt(res['nrc_frame_s'])} s (median after the first frame), OIDN {fmt(res['oidn_s'])} s. "
             f"PT+OIDN at equal time ({fmt(res['equal_time_s'])} s a frame, OIDN included; PT at "
             f"{', '.join(map(str, s['pt_spp']))} spp, {s['pt_repeats']} seeds each): relMSE "
             f"{pm(pt['rel_mse'], pt['rel_mse_ci'])}"
             f"{' (extrapolated)' if pt['extrapolated'] else ''}; raw PT at NRC's frame time "
             f"{fmt(res['pt_raw_rel_mse'])}. NRC+OIDN crosses PT+OIDN at frame **{fmt(res['crossing_frame'])}**.", "",
             "Means over the seeds ± 95 % interval; relMSE over the medium pixels; image mean over the reference's.", "",
             "| frame | NRC relMSE | NRC+OIDN relMSE | NRC mean / ref | NRC+OIDN mean / ref | PT+OIDN relMSE, "
             "equal time | NRC+OIDN / PT+OIDN |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["curve"]:
        cells = [pm(r[k], r[k + "_ci"]) for k in ("rel_mse", "rel_mse_oidn", "mean_ratio", "mean_ratio_oidn")]
        lines.append(f"| {r['frame']} | {' | '.join(cells)} | {fmt(r['pt_oidn_rel_mse'])} | {fmt(r['ratio_oidn'], 2)} |")
    return "\n".join(lines) + "\n"


def summary_markdown(results: list[dict]) -> str:
    """One row per point: its crossing frame, the ratio and the image means at frames 10 and 30."""
    lines = ["NRC+OIDN against PT+OIDN at equal time per frame, from an untrained cache (means over the seeds; "
             "each point's curve.md has the intervals). Image mean / reference's: NRC raw, NRC+OIDN.", "",
             "| point | variant | seeds | crosses at frame | ratio @10 | ratio @30 | mean / ref @10 | mean / ref @30 |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for res in results:
        c, s = res["curve"], res["settings"]
        means = [f"{fmt(at_frame(c, f, 'mean_ratio'))}, {fmt(at_frame(c, f, 'mean_ratio_oidn'))}" for f in (10, 30)]
        lines.append(f"| {res['point']} | {s['label']} | {s['seeds']} | {fmt(res['crossing_frame'])} | "
                     f"{fmt(at_frame(c, 10, 'ratio_oidn'), 2)} | {fmt(at_frame(c, 30, 'ratio_oidn'), 2)} | "
                     f"{means[0]} | {means[1]} |")
    kinds = sorted({r["machine"] for r in results})
    return "\n".join(lines + ["", "Machine: " + "; ".join(kinds)]) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    c, pt = res["curve"], res["pt_oidn"]
    f = np.array([r["frame"] for r in c])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11.5, 4.2))

    def band(axis, key, label, color, clip=None):
        m = np.array([r[key] for r in c], dtype=float)
        h = np.array([r[key + "_ci"] or 0.0 for r in c], dtype=float)
        lo, hi = (m - h, m + h) if clip is None else (np.maximum(m - h, clip), np.maximum(m + h, clip))
        axis.plot(f, m if clip is None else np.maximum(m, clip), "-o", ms=3, color=color, label=label)
        axis.fill_between(f, lo, hi, color=color, alpha=0.25, lw=0)

    band(ax, "rel_mse", "NRC", "tab:blue", TINY)
    band(ax, "rel_mse_oidn", "NRC+OIDN", "tab:orange", TINY)
    if pt["rel_mse"] is not None:
        ax.axhline(pt["rel_mse"], color="k", lw=1, label="PT+OIDN at equal time")
        if pt["rel_mse_ci"]:
            ax.axhspan(max(pt["rel_mse"] - pt["rel_mse_ci"], TINY), pt["rel_mse"] + pt["rel_mse_ci"], color="k",
                       alpha=0.12, lw=0)
    if res["crossing_frame"] is not None:
        ax.axvline(res["crossing_frame"], color="grey", ls=":", lw=1, label=f"crosses at {res['crossing_frame']}")
    ax.set_yscale("log")
    vals = [v for r in c for v in (r["rel_mse"], r["rel_mse_oidn"]) if v > 0] + [pt["rel_mse"] or 0.0]
    if any(v > 0 for v in vals):  # the means in view; a band's lower edge at or below 0 runs off the axis
        ax.set_ylim(0.3 * min(v for v in vals if v > 0), 3 * max(vals))
    ax.set_ylabel("relMSE over the medium (floor-corrected)")
    band(bx, "mean_ratio", "NRC", "tab:blue")
    band(bx, "mean_ratio_oidn", "NRC+OIDN", "tab:orange")
    bx.axhline(1.0, color="k", lw=0.8)
    bx.axhspan(0.97, 1.03, color="green", alpha=0.12, lw=0, label="±3 %")
    bx.set_ylabel("image mean / reference's (medium)")
    for a in (ax, bx):
        a.set_xlabel("frame (from an untrained cache)")
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
        a.grid(True, which="both", lw=0.3)
        a.legend(fontsize=7)
    s = res["settings"]
    fig.suptitle(f"{res['point']} ({s['width']}x{s['height']}, {s['label']}): {s['seeds']} seeds, 95 % bands")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- the measurement
def sides(scene: list[str], args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """The path tracer's and NRC's overrides on ``scene`` (``--backend`` on both; the extra overrides NRC's)."""
    backend = [f"renderer.backend={args.backend}"] if args.backend else []
    return ([*scene, "renderer=pt", "transmittance=ratio", *backend],
            [*scene, "renderer=nrc", "renderer.log.tensorboard=false", *backend, *args.nrc_overrides])


def reference(scene: list[str], ref_spp: int, args: argparse.Namespace) -> Path:
    """The point's reference, rendered here (at least 4 chunks: its noise floor) when missing."""
    from nrc.reference_app import ensure_reference

    return ensure_reference(sides(scene, args)[0], ref_spp, min(args.ref_chunk, max(1, ref_spp // 4)))


def measure(point: str, scene: list[str], ref_spp: int, args: argparse.Namespace) -> dict:
    """The curve of one point (what ``curve.json`` holds)."""
    import torch
    from tqdm import tqdm

    from lab.per_frame import score
    from lab.render import PT_METRICS, SEED_BASE, nrc_run, pt_render, pt_warmup, run_seeds, setup
    from nrc.evaluation.reference import check_independent, read_reference
    from nrc.metrics import medium_mask

    pt_ovs, nrc_ovs = sides(scene, args)
    ref_path = reference(scene, ref_spp, args)
    ref = read_reference(ref_path)
    if ref.alpha is None:
        raise SystemExit(f"learning_curve: reference {ref_path} has no alpha (A channel); re-render it")
    nrc_seeds = run_seeds(args.seeds)
    pt_seeds = [SEED_BASE + 100 * spp + j for spp in args.pt_spp for j in range(args.pt_repeats)]
    check_independent(ref.attrs, [*pt_seeds, *(s + f for s in nrc_seeds for f in range(args.frames))], ref_path)
    floor = ref.rel_mse_floor_medium or 0.0
    image, mask = ref.image.astype(np.float64), medium_mask(ref.alpha)
    oidn: list[float] = []

    def scores(img: np.ndarray) -> dict:
        s = score([img], [image], [mask])
        oidn.append(s["oidn_s"])
        return {"rel_mse": s["rel_mse_medium"] - floor, "rel_mse_oidn": s["rel_mse_medium_oidn"] - floor,
                "mean_ratio": s["mean_ratio_medium"], "mean_ratio_oidn": s["mean_ratio_medium_oidn"]}

    marks = scored_frames(args.frames, args.every)
    nrc = setup(nrc_ovs)
    per_seed, times, nrc_backend = [], [], None
    with tqdm(total=args.seeds * args.frames, desc=f"{point} NRC", unit="frame", disable=args.quiet) as bar:
        for k, seed in enumerate(nrc_seeds):
            images: dict[int, np.ndarray] = {}

            def on_frame(frame, img, output, stats, images=images):
                if frame >= 1 or args.frames == 1:  # the first frame's time holds one-off costs (a compile)
                    times.append(float(stats["time_frame_s"]))
                if frame + 1 in marks:
                    images[frame + 1] = np.nan_to_num(np.asarray(img, np.float64))
                bar.update(1)

            nrc_backend = nrc_run(nrc.scene, nrc.cfg, args.nrc_spp, seed, args.frames, False, on_frame) \
                .metrics.get("backend")
            bar.set_postfix(seed=k + 1)
            per_seed.append([scores(images[f]) for f in marks])  # denoised after the run: never beside its frames
    pt = setup(pt_ovs)
    pt_warmup(pt.scene, pt.cfg)
    pts: dict[int, list[tuple[float, dict]]] = {}
    for spp in tqdm(args.pt_spp, desc=f"{point} PT", unit="spp", disable=args.quiet):
        for j in range(args.pt_repeats):
            img, dt = pt_render(pt.scene, pt.cfg, spp, SEED_BASE + 100 * spp + j)
            pts.setdefault(spp, []).append((dt, scores(img)))
    t_oidn, t_nrc = float(np.median(oidn)), float(np.median(times))
    t_pt = {spp: float(np.mean([dt for dt, _ in v])) for spp, v in pts.items()}

    def front(key: str, extra: float, which: list[int] | None = None) -> float:
        """PT's error ``key`` at equal time (its repeats ``which``, default all, averaged per spp)."""
        points = [(t_pt[spp] + extra, max(TINY, float(np.mean([s[key] for i, (_, s) in enumerate(v)
                                                               if which is None or i in which]))))
                  for spp, v in pts.items()]
        return baseline_error(points, t_nrc + extra)

    pt_oidn = front("rel_mse_oidn", t_oidn)
    _, half = ci95([front("rel_mse_oidn", t_oidn, [j]) for j in range(args.pt_repeats)])
    curve = curve_rows(marks, per_seed, pt_oidn)
    return {
        "point": point, "curve": curve,
        "crossing_frame": crossing_frame(marks, [r["rel_mse_oidn"] for r in curve], pt_oidn),
        "nrc_frame_s": t_nrc, "oidn_s": t_oidn, "equal_time_s": t_nrc + t_oidn, "pt_frame_s": t_pt,
        "pt_oidn": {"rel_mse": pt_oidn, "rel_mse_ci": half,
                    "extrapolated": not min(t_pt.values()) <= t_nrc <= max(t_pt.values())},
        "pt_raw_rel_mse": front("rel_mse", 0.0),
        "pt": {str(spp): [{"time_s": dt, **s} for dt, s in v] for spp, v in pts.items()},
        "nrc_per_seed": [{"seed": seed, "scores": dict(zip(map(str, marks), s))}
                         for seed, s in zip(nrc_seeds, per_seed)],
        "backend": {"requested": args.backend or "auto", "nrc": nrc_backend, "pt": PT_METRICS.get("backend")},
        "reference": {"path": repo_relative(ref_path),
                      "spp": ref.attrs.get("spp"), "rel_mse_floor_medium": ref.rel_mse_floor_medium,
                      "rel_mse_floor": ref.rel_mse_floor, "medium_pixels": int(mask.sum())},
        "settings": {"width": args.width, "height": args.height, "frames": args.frames, "every": args.every,
                     "seeds": args.seeds, "nrc_spp": args.nrc_spp, "pt_spp": args.pt_spp, "pt_repeats": args.pt_repeats,
                     "label": args.label, "nrc_overrides": args.nrc_overrides, "scene": scene, "ref_spp": ref_spp},
        "machine": machine(), "node": platform.node(), "threads": torch.get_num_threads(), "argv": args.argv,
    }


def write_point(res: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "curve.json").write_text(json.dumps(res, indent=1))
    (out / "curve.md").write_text(markdown(res))
    plot(res, out / "curve.png")


def point_order(res: dict) -> int:
    """A result's place in :data:`POINTS` (the crossover map's order: thin to thick, then the albedos)."""
    return list(POINTS).index(res["point"]) if res["point"] in POINTS else len(POINTS)


def write_summary(out: Path) -> Path:
    """``out/summary.md`` over every point in ``out`` (each ``out/<point>/curve.json``)."""
    results = sorted((json.loads(p.read_text()) for p in out.glob("*/curve.json")), key=point_order)
    (out / "summary.md").write_text(summary_markdown(results))
    return out / "summary.md"


def comparison_markdown(results: list[dict], frames: tuple[int, ...] = (5, 10, 20, 30)) -> str:
    """The variants side by side, point by point: NRC's frame time, NRC+OIDN's relMSE at ``frames`` and, in
    parentheses, its ratio to PT+OIDN at equal time (each variant against the path tracer of its own run), NRC+OIDN's
    raw NRC's relMSE at frame 30, NRC+OIDN's image mean at frames 10 and 30, the crossing frame. The relMSE is what to compare variants by: it does not
    depend on the minutes' timings, while the path tracer's equal-time error varies between runs."""
    head = " | ".join(f"@{f}" for f in frames)
    lines = ["NRC+OIDN's relMSE from an untrained cache per variant (means over the seeds) and, in parentheses, its "
             "ratio to PT+OIDN at equal time per frame (below 1: NRC wins; each against the path tracer of its own "
             "run); the raw NRC frame's relMSE at frame 30; NRC+OIDN's image mean over the reference's at frames 10 and 30.",
             "",
             f"| point | variant | NRC overrides | seeds | NRC frame (s) | {head} | raw NRC @30 | mean @10 | mean @30 | "
             "crosses at |",
             "|---|---|---|---:|---:|" + "---:|" * len(frames) + "---:|---:|---:|---:|"]
    for res in sorted(results, key=lambda r: (point_order(r), r["settings"]["label"] != "default",
                                              r["settings"]["label"])):
        c, s = res["curve"], res["settings"]
        cells = " | ".join(f"{fmt(at_frame(c, f, 'rel_mse_oidn'), 3)} ({fmt(at_frame(c, f, 'ratio_oidn'), 2)})"
                           for f in frames)
        lines.append(f"| {res['point']} | {s['label']} | {' '.join(s['nrc_overrides']) or '–'} | {s['seeds']} | "
                     f"{fmt(res['nrc_frame_s'])} | {cells} | {fmt(at_frame(c, 30, 'rel_mse'), 3)} | "
                     f"{fmt(at_frame(c, 10, 'mean_ratio_oidn'))} | "
                     f"{fmt(at_frame(c, 30, 'mean_ratio_oidn'))} | {fmt(res['crossing_frame'])} |")
    kinds = sorted({r["machine"] for r in results})
    return "\n".join(lines + ["", "Machine: " + "; ".join(kinds)]) + "\n"


def write_comparison(root: Path) -> Path:
    """``root/comparison.md`` over every variant in ``root`` (each ``root/<variant>/<point>/curve.json``), each named
    by its folder (a folder renamed to keep an earlier default beside the new one keeps the label it ran under)."""
    results = []
    for p in root.glob("*/*/curve.json"):
        res = json.loads(p.read_text())
        res["settings"]["label"] = p.parent.parent.name
        results.append(res)
    (root / "comparison.md").write_text(comparison_markdown(results))
    return root / "comparison.md"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", default="d0.6,d2,d5,d10", help=f"comma-separated, of {', '.join(POINTS)}")
    p.add_argument("--out", type=Path, default=None, help="default: docs/results/learning_<W>x<H>/<label>")
    p.add_argument("--label", default="default", help="the NRC variant's name (its output folder)")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=90)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--every", type=int, default=1, help="score every k-th frame (and the first and last)")
    p.add_argument("--seeds", type=int, default=5, help="NRC runs from an untrained cache (the interval's n)")
    p.add_argument("--nrc-spp", type=int, default=1)
    p.add_argument("--pt-spp", default="1,2,4", help="the path tracer's spp per frame (its Pareto front)")
    p.add_argument("--pt-repeats", type=int, default=3, help="path-traced frames (seeds) per spp")
    p.add_argument("--backend", default=None, choices=["auto", "eager", "compiled"],
                   help="renderer.backend of both sides (also taken from a renderer.backend=... override)")
    p.add_argument("--ref-spp", type=int, default=None, help="every point's reference spp (default: its own)")
    p.add_argument("--ref-chunk", type=int, default=64, help="spp per chunk of a reference rendered here")
    p.add_argument("--force", action="store_true", help="re-run points whose curve.json exists")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--jobs", choices=["none", "local", "slurm"], default="none",
                   help="each missing point as its own job (submitit): local, one at a time; slurm, a node each")
    p.add_argument("--slurm", action="append", default=[], metavar="KEY=VALUE",
                   help="a Slurm parameter of the jobs (partition=cpu, cpus_per_task=32, timeout_min=120, ...)")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args, args.nrc_overrides = parser().parse_known_args(argv)
    args.argv, args.pt_spp = argv, [int(s) for s in args.pt_spp.split(",")]
    for o in [o for o in args.nrc_overrides if o.startswith("renderer.backend=")]:  # a backend is both sides'
        args.nrc_overrides.remove(o)
        args.backend = o.split("=", 1)[1]
    args.backend = None if args.backend == "auto" else args.backend
    if args.seeds < 1 or args.frames < 1 or args.every < 1:
        raise SystemExit("learning_curve: --seeds, --frames and --every must be >= 1")
    out = (args.out or REPO / "docs" / "results" / f"learning_{args.width}x{args.height}" / args.label).resolve()
    os.chdir(REPO)  # the points' VDB path and the references are relative to the repo root
    points = {}
    for name in args.points.split(","):
        scene, ref_spp = point_scene(name, args.width, args.height, "learning_curve")
        points[name] = (scene, args.ref_spp or ref_spp)
    todo = {n: v for n, v in points.items() if args.force or not (out / n / "curve.json").is_file()}
    if args.jobs != "none" and todo:
        if args.jobs == "slurm":
            require_references(todo, "learning_curve")
        else:  # rendered here, before the jobs: no job renders one while another measures
            for scene, ref_spp in todo.values():
                reference(scene, ref_spp, args)
        script = [sys.executable, str(REPO / "scripts" / "learning_curve.py"), *without_jobs(argv)]
        run_commands({n: [*script, "--points", n, "--out", str(out)] for n in todo}, args.jobs, out / ".jobs", REPO,
                     args.slurm)
    else:
        for name, (scene, ref_spp) in todo.items():
            t0 = time.perf_counter()
            write_point(measure(name, scene, ref_spp, args), out / name)
            print(f"[{name}] done in {time.perf_counter() - t0:.0f} s: {out / name / 'curve.md'}", flush=True)
    print(write_summary(out).read_text())
    print(f"variants side by side: {write_comparison(out.parent)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
