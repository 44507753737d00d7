"""Speed versus error: the path tracer and NRC configurations on one scene and machine, in one invocation
(``python scripts/speed_vs_error.py --help``; the analysis it shares with other tools: :mod:`lab.analysis`).

For every configuration it records (wall time, relMSE, bias, variance) against a converged ``pt``
reference, over the whole image and over the pixels where the reference sees the medium (the
reference's alpha), and writes ``<out>/speed_vs_error.csv``, ``<out>/speed_vs_error.md`` (Markdown
tables with the equal-time error ratios NRC/PT and the crossover), ``<out>/speed_vs_error.png``
(log-log error against time, one curve per configuration) and ``<out>/summary.json``.

Two modes (``--mode single|accumulate|both``):

* **single** (real-time use, equal time per frame). ``pt`` renders ``k`` spp per frame for every ``k``
  in ``--pt-spp``, ``--repeats`` independent frames (seeds) each; NRC renders ``--warmup`` frames of
  on-line training (not scored), then ``--frames`` frames, each scored on its own (``--nrc-spp`` spp per
  frame). Time = mean wall time of one frame (after an untimed warm-up render for ``pt``); relMSE = mean
  over the frames; bias = mean relative bias of the per-pixel mean over the frames; variance = relative
  variance across the frames (see ``nrc.metrics``). The equal-time ratio of an NRC configuration is its
  relMSE over the relMSE of the path tracer (the Pareto front of every ``pt`` configuration run, e.g. the
  eager and compiled backends: the best relMSE reachable within a time) interpolated (log-log) at the same time per frame (extrapolated with slope -1,
  relMSE ~ 1/spp, beyond the slowest point; flat, the fastest frame's error, before the fastest point).
* **accumulate** (static camera; the ``--acc-configs``). ``pt`` accumulates ``--acc-pt-spp``-spp frames,
  NRC accumulates its ``--acc-nrc-spp``-spp frames (default 1; ``renderer.accumulate=true``, training
  continues, counted from a cold cache, after an untimed 16 x 9 warm-up frame like ``pt``'s, whose wall time
  -- the compile or its load from the cache -- is the rows' ``startup_s``); the error of the
  running mean is recorded at 1, 2, 4, ... frames until ``--acc-budget-s`` seconds of rendering (per
  configuration and repeat). ``--acc-repeats`` independent sequences give bias and variance. The
  crossover is the first time after which the unbiased ``pt`` is more accurate than NRC; the accumulated
  equal-time ratios compare each NRC point with the path tracers' running means at its time. ``--acc-startup``
  counts the start-up in those times (the process's imports and scene load, each configuration's warm-up: the
  cold start a user waits for); ``--acc-nrc-frames`` caps NRC's frames apart from the path tracer's;
  ``--acc-nrc-last`` also scores NRC's frame alone (``NAME:last``) beside its running mean.

**As jobs** (``--jobs local|slurm``): each configuration runs as its own submitit job (:mod:`lab.jobs`)
writing its rows to ``<out>/configs/<NAME>.json``; the parent merges them into the same outputs, refusing rows
from different machine types.

The reference is ``--reference`` or ``data/references/reference_<scene hash>_<spp>spp.exr``, rendered
(resumably, by :func:`nrc.reference_app.ensure_reference`) with ``--ref-spp`` spp when missing; its own noise (``rel_mse_floor`` in its header) is
reported next to every relMSE, since each measured relMSE contains it.

Default scene (``--preset disney``): the ``sun`` preset with the shared Disney cloud
(``../shared/data/wdas_cloud_sixteenth.vdb`` relative to the repo root), ``density_scale 0.6``,
160 x 90 pixels; Hydra overrides after the options change it. Example::

    python scripts/speed_vs_error.py --out docs/results/speed_160x90
    python scripts/speed_vs_error.py --out docs/results/speed_480x270 scene.camera.width=480 \\
        scene.camera.height=270 --ref-spp 256 --configs pt,nrc_hashgrid
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lab import REPO, repo_relative
from lab.analysis import DENOISED, add_corrected, all_crossovers, all_ratios, baseline_names, baseline_of
from lab.machine import machine
from lab.render import CPU_TIMES, SEED_BASE, nrc_run, nrc_warmup, pt_render, pt_warmup
from lab.tables import fmt
from nrc.config import CONF_DIR, PRESETS, code_version, compose, preset, resolve_device
from nrc.evaluation.reference import check_independent, default_reference_path, read_reference
from nrc.io.atomic import write_text_atomically
from nrc.metrics import (flicker, hdr_flip, mean_ratio, mean_relative_bias, medium_mask, mse, normalised_rel_mse,
                         rel_mse, relative_variance)
from nrc.reference_app import ensure_reference
from nrc.scene import load_scene


# name -> Hydra overrides. The pt configurations together (their Pareto front) are the baseline of the ratios.
CONFIGS: dict[str, list[str]] = {
    "pt": ["renderer=pt", "transmittance=ratio"],
    "pt_unbiased_raymarch": ["renderer=pt", "transmittance=unbiased_raymarch"],
    "pt_biased_raymarch": ["renderer=pt", "transmittance=biased_raymarch"],
    "nrc_hashgrid": ["renderer=nrc", "encoding=hashgrid_oneblob", "extra_inputs=none", "transmittance=ratio"],
    "nrc_frequency": ["renderer=nrc", "encoding=frequency_oneblob", "extra_inputs=none", "transmittance=ratio"],
    "nrc_triangle": ["renderer=nrc", "encoding=triangle_oneblob", "extra_inputs=none", "transmittance=ratio"],
    "nrc_hashgrid_density": ["renderer=nrc", "encoding=hashgrid_oneblob", "extra_inputs=density",
                             "transmittance=ratio"],
    "nrc_hashgrid_unbiased_raymarch": ["renderer=nrc", "encoding=hashgrid_oneblob", "extra_inputs=none",
                                       "transmittance=unbiased_raymarch"],
    "nrc_hashgrid_biased_raymarch": ["renderer=nrc", "encoding=hashgrid_oneblob", "extra_inputs=none",
                                     "transmittance=biased_raymarch"],
}
DEFAULT_CONFIGS = list(CONFIGS)
# The renderer's own defaults (the training budget sized to the image: renderer.training.width/height=auto);
# runs before 2026-12-02 used a 64 x 64 training image here (--nrc-overrides shows what a run used).
NRC_DEFAULTS = ["renderer.log.tensorboard=false"]
FIELDS = [
    "mode", "config", "renderer", "spp", "frames", "time_s", "cpu_s", "rel_mse", "rel_mse_medium", "rel_mse_corr",
    "rel_mse_medium_corr", "bias", "bias_medium", "mean_ratio", "mean_ratio_medium", "rel_mse_norm",
    "rel_mse_norm_medium", "flip", "flicker_medium", "denoised", "clamp_bias",
    "variance", "variance_medium", "mse", "mse_medium", "renders", "rel_mse_floor", "rel_mse_floor_medium",
]


# ---------------------------------------------------------------------------- config
def parse_configs(names: str, extra: list[str]) -> dict[str, list[str]]:
    """``--configs a,b`` (names from :data:`CONFIGS`) plus ``--config name=ov1,ov2`` definitions."""
    out: dict[str, list[str]] = {}
    for name in [n for n in names.split(",") if n]:
        if name not in CONFIGS:
            raise SystemExit(f"speed_vs_error: unknown config {name!r}; known: {', '.join(CONFIGS)}")
        out[name] = CONFIGS[name]
    for spec in extra:
        name, _, ovs = spec.partition("=")
        out[name] = [o for o in ovs.split(",") if o]
    return out


def renderer_available(name: str) -> bool:
    return (Path(CONF_DIR) / "renderer" / f"{name}.yaml").is_file()


# ---------------------------------------------------------------------------- scoring
@dataclasses.dataclass
class Scorer:
    """Errors of renders against the reference, over all pixels and the medium mask."""

    ref: np.ndarray
    mask: np.ndarray
    floor: float | None
    floor_medium: float | None

    def score(self, frames: list[np.ndarray]) -> dict[str, Any]:
        xs = np.stack(frames).astype(np.float64)
        mask = self.mask if self.mask.any() else None
        row: dict[str, Any] = {"renders": len(xs)}
        for suffix, m in (("", None), ("_medium", mask)):
            if suffix and m is None:
                continue
            row["rel_mse" + suffix] = float(np.mean([rel_mse(x, self.ref, m) for x in xs]))
            row["mse" + suffix] = float(np.mean([mse(x, self.ref, m) for x in xs]))
            row["bias" + suffix] = mean_relative_bias(xs, self.ref, m)
            row["mean_ratio" + suffix] = float(np.mean([mean_ratio(x, self.ref, m) for x in xs]))
            row["rel_mse_norm" + suffix] = float(np.mean([normalised_rel_mse(x, self.ref, m, mask) for x in xs]))
            row["variance" + suffix] = relative_variance(xs, self.ref, m) if len(xs) >= 2 else None
        row["flip"] = _flip(xs, self.ref)
        # consecutive renders of the static camera: NRC's scored frames in order, pt's independent repeats
        row["flicker_medium"] = flicker(xs, self.ref, mask) if len(xs) >= 2 else None
        row["rel_mse_floor"] = self.floor
        row["rel_mse_floor_medium"] = self.floor_medium
        return row


def _flip(xs: np.ndarray, ref: np.ndarray) -> float | None:
    """Mean HDR-FLIP over the renders (whole image), or ``None`` without the ``flip`` extra."""
    try:
        return float(np.mean([hdr_flip(x, ref) for x in xs]))
    except ImportError:
        return None


# ---------------------------------------------------------------------------- modes
def run_single(name, cfg, scene, scorer, args, log) -> list[dict[str, Any]]:
    rows = []

    def emit(spp: int, frames: list, times: list, cpu: list) -> None:
        """One row of mean time per frame and scores (and, with ``--denoise``, its denoised twin)."""
        rows.append({"mode": "single", "config": name, "renderer": cfg.renderer.name, "spp": spp, "frames": 1,
                     "time_s": float(np.mean(times)), "cpu_s": float(np.mean(cpu)), **scorer.score(frames)})
        log(rows[-1])
        if args.denoise:
            rows.append(denoised_row(rows[-1], frames, scorer))
            log(rows[-1])

    if cfg.renderer.name == "pt":
        pt_warmup(scene, cfg)
        for spp in args.pt_spp:
            frames, times, cpu = [], [], []
            for j in range(args.repeats):
                img, dt = pt_render(scene, cfg, spp, SEED_BASE + 100 * spp + j)
                frames.append(img)
                times.append(dt)
                cpu.append(CPU_TIMES[-1])
            emit(spp, frames, times, cpu)
    else:
        for spp in args.nrc_spp:
            frames, times, cpu = [], [], []
            clock = {"c": time.process_time()}

            def cb(frame, image, accumulated, stats, frames=frames, times=times, cpu=cpu, clock=clock):
                now = time.process_time()  # CPU time since the previous frame's callback: this frame's
                if frame >= args.warmup:
                    frames.append(np.nan_to_num(np.asarray(image, np.float64)))
                    times.append(float(stats["time_frame_s"]))
                    cpu.append(now - clock["c"])
                clock["c"] = time.process_time()

            for k in range(args.nrc_repeats):  # independent runs (their own seeds), frames pooled
                nrc_run(scene, cfg, spp, SEED_BASE + spp + 7919 * k, args.warmup + args.frames, False, cb)
            emit(spp, frames, times, cpu)
    return rows


def denoised_row(row: dict[str, Any], frames: list[np.ndarray], scorer: Scorer) -> dict[str, Any]:
    """The twin of a single-frame row with every frame denoised by OIDN; the denoise time (median over the
    frames, measured now) is added to its time per frame."""
    from nrc.denoise import clamp_bias, denoise

    out, times, cpu = [], [], []
    for f in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        out.append(denoise(f).astype(np.float64))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    twin = {**row, "config": row["config"] + DENOISED, "denoised": True, **scorer.score(out)}
    twin["time_s"] = row["time_s"] + float(np.median(times))
    twin["cpu_s"] = None if row.get("cpu_s") is None else row["cpu_s"] + float(np.median(cpu))
    twin["time_denoise_s"] = float(np.median(times))
    twin["clamp_bias"] = float(np.mean([clamp_bias(f) for f in frames]))  # the denoiser's copy drops negatives
    return twin


def checkpoints(n_max: int) -> list[int]:
    """1, 2, 4, ... up to ``n_max``, and ``n_max`` itself (e.g. 30 frames: ..., 16, 30)."""
    out, n = [], 1
    while n <= n_max:
        out.append(n)
        n *= 2
    return out if out[-1] == n_max else out + [n_max]


def run_accumulate(name, cfg, scene, scorer, args, log) -> list[dict[str, Any]]:
    """Error of the running mean at 1, 2, 4, ... frames; ``acc_repeats`` independent sequences."""
    nrc_frames = args.acc_nrc_frames or args.acc_max_frames
    marks = sorted(set(checkpoints(args.acc_max_frames)) | (set() if cfg.renderer.name == "pt" else {nrc_frames}))
    seqs: list[dict[int, tuple[float, np.ndarray]]] = []  # per repeat: frames -> (cumulative time, mean)
    lasts: list[dict[int, tuple[float, np.ndarray]]] = []  # NRC with --acc-nrc-last: frames -> (time, that frame)
    for rep in range(args.acc_repeats):
        rec: dict[int, tuple[float, np.ndarray]] = {}
        last: dict[int, tuple[float, np.ndarray]] = {}
        if cfg.renderer.name == "pt":
            if rep == 0:
                t0 = time.perf_counter()
                pt_warmup(scene, cfg)
                startup = time.perf_counter() - t0
            total, t_cum = None, 0.0
            for i in range(args.acc_max_frames):
                img, dt = pt_render(scene, cfg, args.acc_pt_spp, SEED_BASE + 10_000 * (rep + 1) + i)
                total = img.astype(np.float64) if total is None else total + img
                t_cum += dt
                if i + 1 in marks:
                    rec[i + 1] = (t_cum, total / (i + 1))
                if t_cum > args.acc_budget_s:
                    break
        else:
            if rep == 0:
                startup = nrc_warmup(scene, cfg)
            state = {"t": 0.0}

            class Stop(Exception):
                pass

            def cb(frame, image, accumulated, stats, rec=rec, last=last, state=state):
                state["t"] += float(stats["time_frame_s"])
                if frame + 1 in marks:
                    rec[frame + 1] = (state["t"], np.nan_to_num(np.asarray(accumulated, np.float64)))
                    if args.acc_nrc_last:
                        last[frame + 1] = (state["t"], np.nan_to_num(np.asarray(image, np.float64)))
                if state["t"] > args.acc_budget_s:
                    raise Stop

            try:
                nrc_run(scene, cfg, args.acc_nrc_spp, SEED_BASE + 20_000 * (rep + 1), nrc_frames, True, cb)
            except Stop:
                pass
        seqs.append(rec)
        lasts.append(last)
    rows = []
    spp = args.acc_pt_spp if cfg.renderer.name == "pt" else args.acc_nrc_spp
    for config, runs in ((name, seqs), (name + LAST, lasts)):
        if not all(runs):
            continue
        for n in sorted(set.intersection(*(set(r) for r in runs))):
            render_s = float(np.mean([r[n][0] for r in runs]))
            # the warm-up (compile or cache load, 16 x 9), and with --acc-startup the process's own start-up too
            row = {"mode": "accumulate", "config": config, "renderer": cfg.renderer.name, "spp": spp, "frames": n,
                   "render_s": render_s, "startup_s": startup, "process_startup_s": args.process_startup_s,
                   "time_s": render_s + (startup + args.process_startup_s if args.acc_startup else 0.0),
                   "startup_counted": bool(args.acc_startup), **scorer.score([r[n][1] for r in runs])}
            rows.append(row)
            log(row)
            if args.denoise:  # the image denoised at this point (its time + one denoise)
                rows.append(denoised_row(row, [r[n][1] for r in runs], scorer))
                log(rows[-1])
    return rows


LAST = ":last"  # NRC's frame alone at an accumulated point (--acc-nrc-last), beside its running mean


# ---------------------------------------------------------------------------- analysis


# ---------------------------------------------------------------------------- outputs


def black_baseline(ref_path: Path) -> dict[str, float]:
    """relMSE of an all-black image against the reference: what a renderer that gives up scores."""
    ref = read_reference(ref_path)
    black = np.zeros_like(ref.image)
    m = medium_mask(ref.alpha) if ref.alpha is not None else None
    return {"rel_mse": rel_mse(black, ref.image),
            "rel_mse_medium": rel_mse(black, ref.image, m) if m is not None and m.any() else None}


def write_outputs(out: Path, rows, ratios, cross, meta) -> None:
    out.mkdir(parents=True, exist_ok=True)
    if "black" not in meta:
        ref_path = Path(meta["reference"])
        meta["black"] = black_baseline(ref_path if ref_path.is_absolute() else REPO / ref_path)
    add_corrected(rows, meta["rel_mse_floor"], meta["rel_mse_floor_medium"])
    with open(out / "speed_vs_error.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in FIELDS})
    ratios_cpu = all_ratios(rows, baseline_names(meta.get("baseline")), "cpu_s")
    meta["equal_cpu_time"] = ratios_cpu
    (out / "summary.json").write_text(json.dumps({"meta": meta, "rows": rows, "equal_time": ratios,
                                                  "equal_cpu_time": ratios_cpu, "crossover": cross}, indent=2))
    (out / "speed_vs_error.md").write_text(markdown(rows, ratios, cross, meta))
    plot(out / "speed_vs_error.png", rows, meta)


def markdown(rows, ratios, cross, meta) -> str:
    lines = [f"Scene: {meta['scene']}, {meta['width']}x{meta['height']} pixels. Reference: {meta['reference']} "
             f"({meta['ref_spp']} spp; its own noise adds rel_mse_floor = {fmt(meta['rel_mse_floor'])} over all "
             f"pixels, {fmt(meta['rel_mse_floor_medium'])} over the medium, to every relMSE below). "
             f"Medium pixels: {meta['medium_pixels']} of {meta['width'] * meta['height']}. "
             f"Machine: {meta['machine']}. Wall time of the whole run: {meta['wall_time_s']:.0f} s. "
             f"NRC settings added to every NRC config: `{' '.join(meta['nrc_overrides'])}`. Code: {meta['git']}.", "",
             f"Sanity baseline: an all-black image scores relMSE {fmt(meta['black']['rel_mse_medium'])} over the "
             f"medium pixels ({fmt(meta['black']['rel_mse'])} over all): a renderer below that is not necessarily "
             "right, and one above it is noisier than giving up. Flicker: the mean |I_t - I_t-1| over the medium "
             "pixels over the reference's mean there, for consecutive frames of the static camera (NRC's scored "
             "frames in order; pt's independent renders).", ""]
    for mode, title in (("single", "Single frames (time = wall time per frame)"),
                        ("accumulate", "Accumulated frames, static camera (time = cumulative wall time")):
        sel = [r for r in rows if r["mode"] == mode]
        if not sel:
            continue
        if mode == "accumulate":
            title += (", start-up included: the process's imports, scene and reference load and each configuration's "
                      "warm-up frame, i.e. the compile or its load from the cache)"
                      if any(r.get("startup_counted") for r in sel) else ")")
        lines += [f"**{title}**", "",
                  "| config | spp/frame | frames | time (s) | CPU time (s) | relMSE medium | relMSE all | "
                  "relMSE medium, normalised | mean / reference, medium | rel. bias medium | rel. variance medium "
                  "| HDR-FLIP | flicker medium | renders |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in sel:
            lines.append(f"| {r['config']} | {r['spp']} | {r['frames']} | {r['time_s']:.3g} | {fmt(r.get('cpu_s'))} | "
                         f"{fmt(r.get('rel_mse_medium'))} | {fmt(r['rel_mse'])} | {fmt(r.get('rel_mse_norm_medium'))} | "
                         f"{fmt(r.get('mean_ratio_medium'))} | {fmt(r.get('bias_medium'))} | "
                         f"{fmt(r.get('variance_medium'))} | {fmt(r.get('flip'))} | {fmt(r.get('flicker_medium'))} | "
                         f"{r['renders']} |")
        lines.append("")
    if ratios:
        pts = ", ".join(f"`{n}`" for n in baseline_names(meta["baseline"]))
        lines += [f"**Equal time per frame**: NRC relMSE over the path tracer's relMSE (the Pareto front of {pts}) "
                  "interpolated (log-log) at the NRC time per frame (between the front's slowest point and PT's slowest "
                  "measured frame flat: that time was measured not to help; beyond every measured frame extrapolated with "
                  "relMSE ~ 1/time; below its fastest frame, PT's fastest frame's error: a frame cannot take less than "
                  "PT's smallest spp). Accumulated rows (a static camera): the running means at equal cumulative "
                  "time, start-up included where the accumulated table says so.", "",
                  "The corrected ratio subtracts the reference's noise floor from both relMSEs first.", "",
                  "| config | against | spp/frame | time/frame (s) | NRC relMSE medium | PT relMSE medium at equal "
                  "time | ratio medium | ratio all | ratio medium, floor-corrected | PT extrapolated |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
        for q in ratios:
            what = q["config"] + (f" (accumulated, {q['frames']} frames)" if q.get("mode") == "accumulate" else "")
            lines.append(f"| {what} | {q.get('baseline', 'pt')} | {q['spp']} | {q['time_s']:.3g} | "
                         f"{fmt(q.get('pt_rel_mse_medium') and q['ratio_rel_mse_medium'] * q['pt_rel_mse_medium'])} | "
                         f"{fmt(q.get('pt_rel_mse_medium'))} | {fmt(q.get('ratio_rel_mse_medium'), 2)} | "
                         f"{fmt(q.get('ratio_rel_mse'), 2)} | {fmt(q.get('ratio_rel_mse_medium_corr'), 2)} | "
                         f"{'yes' if q.get('extrapolated') else 'no'} |")
        lines.append("")
    if meta.get("equal_cpu_time"):
        lines += ["**Equal CPU time per frame** (process CPU time of all threads instead of wall time: less "
                  "sensitive to other jobs on the machine):", "",
                  "| config | CPU s/frame | ratio medium | ratio all | ratio medium, floor-corrected | PT extrapolated |",
                  "|---|---:|---:|---:|---:|---|"]
        for q in meta["equal_cpu_time"]:
            lines.append(f"| {q['config']} | {q['time_s']:.3g} | {fmt(q.get('ratio_rel_mse_medium'), 2)} | "
                         f"{fmt(q.get('ratio_rel_mse'), 2)} | {fmt(q.get('ratio_rel_mse_medium_corr'), 2)} | "
                         f"{'yes' if q.get('extrapolated') else 'no'} |")
        lines.append("")
    if cross:
        lines += ["**Crossover (accumulated, static camera)**: the time after which the unbiased PT's running mean "
                  f"has the lower {cross[0]['metric']} (compared from PT's first frame on; \"<=\": PT is already "
                  "ahead with its first frame).", "",
                  "| config | against | crossover (s) | measured up to (s) |", "|---|---|---:|---:|"]
        for c in cross:
            t = "none within the budget" if c["crossover_time_s"] is None else \
                ("<= " if c.get("crossover_at_or_before") else "") + fmt(c["crossover_time_s"])
            lines.append(f"| {c['config']} | {c.get('baseline', 'pt')} | {t} | {fmt(c['max_time_s'])} |")
        lines.append("")
    return "\n".join(lines)


def plot(path: Path, rows, meta) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [m for m in ("single", "accumulate") if any(r["mode"] == m for r in rows)]
    fig, axes = plt.subplots(1, len(modes), figsize=(7.6 * len(modes), 4.8), squeeze=False)
    key = "rel_mse_medium" if any(r.get("rel_mse_medium") is not None for r in rows) else "rel_mse"
    floor = meta["rel_mse_floor_medium"] if key == "rel_mse_medium" else meta["rel_mse_floor"]
    for ax, mode in zip(axes[0], modes):
        for name in dict.fromkeys(r["config"] for r in rows if r["mode"] == mode):
            c = sorted((r for r in rows if r["mode"] == mode and r["config"] == name), key=lambda r: r["time_s"])
            style = "-o" if c[0]["renderer"] == "pt" else "--s"
            ax.loglog([r["time_s"] for r in c], [r[key] for r in c], style, ms=4, label=name)
        if floor:
            ax.axhline(floor, color="grey", lw=0.8, ls=":", label="reference noise floor")
        ax.set_xlabel("wall time per frame (s)" if mode == "single" else "cumulative wall time (s)")
        ax.set_ylabel("relMSE over medium pixels" if key == "rel_mse_medium" else "relMSE")
        ax.set_title(f"{'single frames' if mode == 'single' else 'accumulated, static camera'} — "
                     f"{meta['width']}x{meta['height']}")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def get_reference(cfg, args, log) -> tuple[Path, Any]:
    """The reference EXR: ``--reference``, or the default file for this scene (rendered when missing)."""
    path = args.reference or default_reference_path(cfg, args.ref_spp)
    if not args.reference and not path.is_file():
        log(f"rendering the reference {path} ({args.ref_spp} spp)")
        path = ensure_reference([*args.scene_overrides, "renderer=pt", "transmittance=ratio",
                                 "renderer.backend=compiled"], args.ref_spp, args.ref_chunk, progress=args.progress)
    ref = read_reference(path)
    check_independent(ref.attrs, range(SEED_BASE, SEED_BASE + 10_000), path)
    return path, ref


def run(args: Any, overrides: list[str], argv: list[str]) -> int:
    """The measurement of ``scripts/speed_vs_error.py`` (its options in ``args``, scene overrides after the
    preset's in ``overrides``; ``argv`` is recorded in the summary)."""
    args.pt_spp = [int(s) for s in args.pt_spp.split(",")]
    args.nrc_spp = [int(s) for s in args.nrc_spp.split(",")]
    args.scene_overrides = preset(args.preset) + overrides
    args.nrc_overrides = [o for o in args.nrc_overrides.split(",") if o]
    if args.threads:
        torch.set_num_threads(args.threads)

    def log(msg: Any) -> None:
        if args.quiet:
            return
        if isinstance(msg, dict):
            msg = (f"{msg['mode']:10s} {msg['config']:32s} spp={msg['spp']} frames={msg['frames']} "
                   f"t={msg['time_s']:.3g}s relMSE={fmt(msg['rel_mse'])} medium={fmt(msg.get('rel_mse_medium'))}")
        print(msg, flush=True)

    start = time.perf_counter()
    configs = parse_configs(args.configs, args.config)
    if args.only:
        if args.only not in configs:
            raise SystemExit(f"speed_vs_error: --only {args.only!r} is not one of the configurations "
                             f"({', '.join(configs)})")
        configs = {args.only: configs[args.only]}
    base_cfg = compose(args.scene_overrides)
    if args.jobs != "none" and not args.only:
        return run_as_jobs(args, argv, configs, base_cfg, log)
    startup = since_process_start()
    ref_path, ref = get_reference(base_cfg, args, log)
    t0 = time.perf_counter()
    scene = load_scene(base_cfg.scene, resolve_device(base_cfg.device))
    args.process_startup_s = startup + time.perf_counter() - t0  # imports, config, scene (not a reference render)
    cam = scene.camera
    if ref.image.shape != (cam.height, cam.width, 3):
        raise SystemExit(f"speed_vs_error: reference {ref_path} is {ref.image.shape}, scene is {cam.height}x{cam.width}")
    if ref.alpha is None:
        raise SystemExit(f"speed_vs_error: reference {ref_path} has no alpha (A channel); re-render it")
    mask = medium_mask(ref.alpha)
    scorer = Scorer(ref.image.astype(np.float64), mask, ref.rel_mse_floor, ref.rel_mse_floor_medium)

    rows: list[dict[str, Any]] = []
    skipped: list[str] = []

    def finish() -> tuple[dict, list, list]:
        """Ratios, crossovers and outputs from the rows so far (written after every configuration)."""
        baseline = [n for n, o in configs.items() if _renderer_of(o) == "pt" and n not in skipped] or None
        cross = all_crossovers(rows, baseline)
        meta = {
            # paths relative to the repo root (../shared/...), never this machine's
            "scene": " ".join(args.scene_overrides).replace(str(REPO.parent) + "/", "../") or "defaults", "width": cam.width, "height": cam.height,
            "reference": repo_relative(ref_path),
            "ref_spp": ref.attrs.get("spp"), "rel_mse_floor": ref.rel_mse_floor,
            "rel_mse_floor_medium": ref.rel_mse_floor_medium, "medium_pixels": int(mask.sum()),
            "baseline": baseline, "skipped": skipped, "nrc_overrides": args.nrc_overrides,
            "git": code_version(), "argv": argv,
            "machine": machine(), "machine_type": machine(), "node": platform.node(),
            "threads": torch.get_num_threads(),
            "wall_time_s": time.perf_counter() - start,
        }
        add_corrected(rows, ref.rel_mse_floor, ref.rel_mse_floor_medium)
        ratios = all_ratios(rows, baseline)
        if args.only:  # one configuration of a run as jobs: its rows only, merged by the parent
            write_text_atomically(part_path(args.out, args.only), json.dumps({"meta": meta, "rows": rows}, indent=2))
        else:
            write_outputs(args.out, rows, ratios, cross, meta)
        return meta, ratios, cross

    for name, ovs in configs.items():
        nrc_defaults = args.nrc_overrides if _renderer_of(ovs) == "nrc" else []
        cfg = compose(args.scene_overrides + nrc_defaults + ovs) if renderer_available(_renderer_of(ovs)) else None
        if cfg is None:
            skipped.append(name)
            log(f"skipping {name}: renderer {_renderer_of(ovs)!r} is not available")
            continue
        if args.mode in ("single", "both"):
            rows += run_single(name, cfg, scene, scorer, args, log)
        if args.mode in ("accumulate", "both") and (args.acc_configs == "all" or name in args.acc_configs.split(",")):
            rows += run_accumulate(name, cfg, scene, scorer, args, log)
        finish()
    meta, ratios, cross = finish()
    baseline = "+".join(baseline_names(meta["baseline"]))
    for q in ratios:
        log(f"equal-time relMSE ratio {q['config']}/{q.get('baseline', baseline)} (spp {q['spp']}): "
            f"medium {fmt(q.get('ratio_rel_mse_medium'), 2)}, all {fmt(q.get('ratio_rel_mse'), 2)}")
    for c in cross:
        log(f"crossover {c['config']} vs {c.get('baseline', baseline)}: {fmt(c['crossover_time_s'])} s")
    log(f"wrote {args.out}/speed_vs_error.{{csv,md,png}} and summary.json in {meta['wall_time_s']:.0f} s")
    return 0


def part_path(out: Path, name: str) -> Path:
    """Where the job of configuration ``name`` writes its rows (``--jobs``)."""
    return Path(out) / "configs" / f"{name}.json"


def run_as_jobs(args: Any, argv: list[str], configs: dict[str, list[str]], base_cfg, log) -> int:
    """``--jobs local|slurm``: each configuration as its own launcher job (:mod:`lab.jobs`), which
    writes its rows to :func:`part_path`; then the tables, ratios and plot of the rows together, as one process
    would write them, refusing rows from different machine types. A configuration whose rows exist is not run
    again (delete them to re-measure). The reference is rendered first, here (``local``), or must exist
    (``slurm``: ``python -m nrc.reference_app``, docs/running.md)."""
    from lab.jobs import check_one_machine_type, run_commands, without_jobs

    start = time.perf_counter()
    path = args.reference or default_reference_path(base_cfg, args.ref_spp)
    if args.jobs == "slurm" and not path.is_file():
        raise SystemExit(f"speed_vs_error: no reference {path}: render it first, e.g. python -m nrc.reference_app "
                         f"{' '.join(args.scene_overrides)} scene.integrator.spp={args.ref_spp} (docs/running.md)")
    ref_path, ref = get_reference(base_cfg, args, log)
    script = REPO / "scripts" / "speed_vs_error.py"
    todo = {name: [sys.executable, str(script), *without_jobs(argv), "--only", name]
            for name in configs if not part_path(args.out, name).is_file()}
    nodes = run_commands(todo, args.jobs, Path(args.out) / ".jobs", REPO, args.slurm) if todo else {}
    parts = {name: json.loads(part_path(args.out, name).read_text()) for name in configs}
    check_one_machine_type(parts, "speed_vs_error")
    rows = [r for p in parts.values() for r in p["rows"]]
    baseline = baseline_of(rows)
    first = next(iter(parts.values()))["meta"]
    meta = {**first, "argv": argv, "baseline": baseline, "skipped": [s for p in parts.values() for s in p["meta"]["skipped"]],
            "nodes": {name: p["meta"].get("node") for name, p in parts.items()},
            "jobs": args.jobs, "wall_time_s": time.perf_counter() - start,
            "job_wall_time_s": {name: p["meta"]["wall_time_s"] for name, p in parts.items()}}
    meta["reference"] = repo_relative(ref_path)
    meta["node"] = ", ".join(dict.fromkeys(str(n) for n in meta["nodes"].values()))
    add_corrected(rows, ref.rel_mse_floor, ref.rel_mse_floor_medium)
    write_outputs(args.out, rows, all_ratios(rows, baseline), all_crossovers(rows, baseline), meta)
    log(f"merged {len(parts)} configurations ({len(todo)} run now{', on ' + meta['node'] if nodes else ''}) "
        f"into {args.out}/summary.json")
    return 0


def since_process_start() -> float:
    """Seconds since this process started (Linux ``/proc``; else 0): its imports, which a user waits for too."""
    import os

    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime"))
        return max(0.0, time.time() - (boot + ticks / os.sysconf("SC_CLK_TCK")))
    except (OSError, ValueError, IndexError, StopIteration):
        return 0.0


def replot(out: Path) -> int:
    """Recompute ratios, crossovers, Markdown and plot from ``out/summary.json``."""
    summary = json.loads((out / "summary.json").read_text())
    rows, meta = summary["rows"], summary["meta"]
    meta.setdefault("nrc_overrides", [])
    meta.setdefault("git", "unknown")
    add_corrected(rows, meta["rel_mse_floor"], meta["rel_mse_floor_medium"])
    # every pt configuration of the run is part of the baseline (older summaries named only the first)
    baseline = meta["baseline"] = baseline_of(rows)
    write_outputs(out, rows, all_ratios(rows, baseline), all_crossovers(rows, baseline), meta)
    print(f"rewrote {out}")
    return 0


def _renderer_of(overrides: list[str]) -> str:
    for o in overrides:
        if o.startswith("renderer="):
            return o.split("=", 1)[1]
    return "pt"


# ---------------------------------------------------------------------------- command line
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=REPO / "outputs" / "speed_vs_error")
    p.add_argument("--preset", choices=PRESETS, default="disney", help="scene overrides applied first")
    p.add_argument("--mode", choices=["single", "accumulate", "both"], default="both")
    p.add_argument("--configs", default=",".join(DEFAULT_CONFIGS), help="comma-separated names (see CONFIGS)")
    p.add_argument("--config", action="append", default=[], metavar="NAME=OV1,OV2", help="a custom configuration")
    p.add_argument("--pt-spp", default="1,2,4,8", help="pt spp per frame (single mode)")
    p.add_argument("--nrc-spp", default="1", help="NRC spp per frame (single mode)")
    p.add_argument("--repeats", type=int, default=3, help="independent pt frames per spp (single mode)")
    p.add_argument("--warmup", type=int, default=10, help="NRC training frames before scoring (single mode)")
    p.add_argument("--frames", type=int, default=4, help="scored NRC frames (single mode)")
    p.add_argument("--nrc-repeats", type=int, default=1,
                   help="independent NRC runs per configuration (single mode; their scored frames are pooled: the "
                        "spread between runs of the online training shows in the variance)")
    p.add_argument("--acc-max-frames", type=int, default=256, help="most frames accumulated (accumulate mode)")
    p.add_argument("--acc-nrc-frames", type=int, default=None,
                   help="NRC's frames in accumulate mode (default --acc-max-frames; scored there too), e.g. 30 with a "
                        "larger --acc-max-frames for the path tracer, which then runs until --acc-budget-s")
    p.add_argument("--acc-nrc-last", action="store_true",
                   help="also score NRC's frame alone at each accumulated point (config NAME:last): after a cold "
                        "start its running mean still holds the untrained cache's first frames")
    p.add_argument("--acc-budget-s", type=float, default=60.0, help="render seconds per sequence (accumulate)")
    p.add_argument("--acc-repeats", type=int, default=2, help="independent sequences (accumulate mode)")
    p.add_argument("--acc-pt-spp", type=int, default=4,
                   help="spp per accumulated pt frame (a wavefront frame costs about the same at 1-4 spp)")
    p.add_argument("--acc-nrc-spp", type=int, default=1, help="NRC spp per accumulated frame (accumulate mode)")
    p.add_argument("--acc-startup", action="store_true",
                   help="count start-up in the accumulated times (the process's imports and scene load, and each "
                        "configuration's warm-up: the compile or its load): the cold-start comparison a user waits for")
    p.add_argument("--acc-configs", default="pt,nrc_hashgrid",
                   help="configurations also run in accumulate mode (comma-separated; 'all' for every one)")
    p.add_argument("--nrc-overrides", default=",".join(NRC_DEFAULTS),
                   help="Hydra overrides applied to every nrc configuration before its own (comma-separated)")
    p.add_argument("--denoise", action="store_true",
                   help="also score every configuration denoised by OIDN (single frames; accumulated: the running "
                        "mean at each point), time + denoise time")
    p.add_argument("--reference", type=Path, default=None)
    p.add_argument("--ref-spp", type=int, default=512)
    p.add_argument("--ref-chunk", type=int, default=64)
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    p.add_argument("--skip-missing", action="store_true", default=True,
                   help="skip configurations whose renderer is not available (default)")
    p.add_argument("--progress", action="store_true", help="progress bar for a reference render")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--jobs", choices=["none", "local", "slurm"], default="none",
                   help="run each configuration as its own launcher job (submitit; local: one after another, slurm: "
                        "a node each, --exclusive), then merge their rows (refusing mixed machine types)")
    p.add_argument("--slurm", action="append", default=[], metavar="KEY=VALUE",
                   help="a Slurm parameter of the jobs (partition=cpu, cpus_per_task=32, timeout_min=120, ...)")
    p.add_argument("--only", default=None, metavar="NAME",
                   help="run only this configuration and write its rows to OUT/configs/NAME.json (what a job runs)")
    p.add_argument("--replot", type=Path, default=None, metavar="DIR",
                   help="only rewrite the tables and plot of DIR/summary.json (no rendering)")
    return p


def main(argv: list[str] | None = None) -> int:
    args, overrides = parser().parse_known_args(argv)
    if args.replot:
        return replot(args.replot)
    return run(args, overrides, sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
