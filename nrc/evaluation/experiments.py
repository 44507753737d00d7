"""Tables and plots of the thesis experiments (``conf/experiment/*.yaml`` Hydra multiruns).

Each experiment is a multirun ``python -m nrc +experiment=<name>`` (run from the repo root) that writes
its jobs to ``multirun/experiments/<name>/<job number>/`` (``metrics.json``, ``image.exr``,
``.hydra/config.yaml``, ``.hydra/overrides.yaml``). This script reads them and writes, per report,
``<docs>/results/<report>.md`` (Markdown tables with the reproducing commands, the machine and the wall
time of each multirun, taken from its files' timestamps) and ``<docs>/images/results/<report>*.png``.

Reports (the experiments they read):

* ``encodings`` (encodings): inference and training time per frame and the loss after N frames, per
  encoding x MLP width x depth (thesis Fig. 5.5).
* ``extra_inputs`` (extra_inputs): training-loss curves over frames (Fedotov Fig. 6.1/6.3).
* ``batch_filters`` (batch_filters): training time per frame per filter and camera framing (Fedotov Table 6.1).
* ``transmittance`` (transmittance_pt, transmittance_nrc): relMSE, bias and variance over seeds and time
  per frame of the path tracer, and the NRC loss and time per frame, per estimator (Fedotov Fig. 6.16/6.17).
* ``nrc_vs_pt`` (nrc_vs_pt_pt, nrc_vs_pt_nrc): MSE, relative bias and relative variance of NRC and PT at
  1 spp, recommended and thesis definitions side by side (Spindler Fig. 5.8-5.10).

Error metrics need a converged reference of the run's scene: ``data/references/reference_<scene
hash>_<spp>spp.exr`` (the highest spp found), rendered with ``scripts/render_reference.py``.

Usage::

    python scripts/experiments_report.py [encodings extra_inputs batch_filters transmittance nrc_vs_pt] [--results]

``--results`` then assembles ``docs/results.md`` from ``docs/results_intro.md`` (hand-written), the
``scripts/speed_vs_error.py`` outputs listed in :data:`SPEED_RUNS` (``docs/results/speed_*``), and the report
fragments.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[2]  # the checkout (multirun/, docs/, data/references live there)

from nrc.io import read_exr  # noqa: E402
from nrc.evaluation.metrics import error_report, medium_mask  # noqa: E402
from nrc.evaluation.reference import read_reference, scene_hash  # noqa: E402

from nrc.evaluation.speed_vs_error import fmt  # noqa: E402  (one number format for every generated table)

REF_DIR = REPO / "data" / "references"
REPORTS: dict[str, list[str]] = {
    "encodings": ["encodings"],
    "extra_inputs": ["extra_inputs"],
    "batch_filters": ["batch_filters"],
    "transmittance": ["transmittance_pt", "transmittance_nrc"],
    "nrc_vs_pt": ["nrc_vs_pt_pt", "nrc_vs_pt_nrc"],
}


# ---------------------------------------------------------------------------- loading
def load_runs(root: Path, experiment: str) -> list[dict[str, Any]]:
    """Every finished job of ``root/<experiment>``: overrides, config, metrics and image path."""
    runs = []
    base = root / experiment
    if not base.is_dir():
        return runs
    for job in sorted((p for p in base.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)):
        mfile = job / "metrics.json"
        if not mfile.is_file():
            continue
        ovs = OmegaConf.to_container(OmegaConf.load(job / ".hydra" / "overrides.yaml"))
        runs.append({
            "dir": job, "overrides": ovs, "cfg": OmegaConf.load(job / ".hydra" / "config.yaml"),
            "metrics": json.loads(mfile.read_text()), "image": job / "image.exr",
            "choices": _choices(job),
        })
    return runs


def _choices(job: Path) -> dict[str, str]:
    hydra_cfg = OmegaConf.load(job / ".hydra" / "hydra.yaml")
    return {str(k): str(v) for k, v in hydra_cfg.hydra.runtime.choices.items()}


def wall_time(root: Path, experiment: str) -> float | None:
    """Seconds from the first job's config to the last job's metrics (the multirun's wall time)."""
    base = root / experiment
    starts = [p.stat().st_mtime for p in base.glob("*/.hydra/config.yaml")]
    ends = [p.stat().st_mtime for p in base.glob("*/metrics.json")]
    if not starts or not ends:
        return None
    return max(ends) - min(starts)


def find_reference(cfg) -> Path | None:
    """The highest-spp reference for the run's scene under data/references/ (``None`` if there is none)."""
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    for item in [cfg.scene.volume, *(cfg.scene.get("lights") or [])]:
        if item.get("path") and not os.path.isabs(item.path):
            item.path = str(REPO / item.path)
    h = scene_hash(cfg)[:12]
    found = sorted(REF_DIR.glob(f"reference_{h}_*spp.exr"),
                   key=lambda p: int(p.stem.rsplit("_", 1)[1][:-3]))
    return found[-1] if found else None


CONDITIONS = {"text": "run conditions not recorded"}  # --conditions: how the multiruns were run


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}; {CONDITIONS['text']}"


def mean_after_first(xs: list[float]) -> float | None:
    """Mean per-frame value without frame 0 (start-up); the only value when there is one frame."""
    xs = list(xs or [])
    if not xs:
        return None
    return float(np.mean(xs[1:] if len(xs) > 1 else xs))


def header(title: str, experiments: list[str], root: Path, what: str) -> list[str]:
    cmds = " && ".join(f"`python -m nrc +experiment={e}`" for e in experiments)
    times = [wall_time(root, e) for e in experiments]
    took = ", ".join(f"{e}: {fmt(t, 3)} s" for e, t in zip(experiments, times))
    return [f"### {title}", "", what, "",
            f"Reproduce (repo root): {cmds}, then `python scripts/experiments_report.py "
            f"{next(k for k, v in REPORTS.items() if v == experiments)}`. Machine: {machine()}. "
            f"Wall time of the multirun(s): {took}.", ""]


def plt_setup():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ---------------------------------------------------------------------------- reports
def report_encodings(root: Path, images: Path) -> list[str]:
    runs = load_runs(root, "encodings")
    lines = header("Encodings x MLP width x depth (thesis Fig. 5.5)", ["encodings"], root,
                   "Per-frame inference and training time (mean over frames 1..N-1; frame 0 includes start-up) "
                   "and the training loss of the last frame (relative L2, mean over the frame's batches).")
    if not runs:
        return lines + ["(no runs found)", ""]
    n_frames = runs[0]["metrics"].get("frames")
    lines += [f"| encoding | width | hidden layers | parameters | inference (s/frame) | training (s/frame) | "
              f"frame (s) | loss after {n_frames} frames |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    rows = []
    for r in runs:
        m, net = r["metrics"], r["cfg"].cache.network
        rows.append((r["choices"].get("encoding"), int(net.n_neurons), int(net.n_hidden_layers),
                     m.get("cache_parameters"), mean_after_first(m.get("time_infer_s")),
                     mean_after_first(m.get("time_train_s")), mean_after_first(m.get("frame_times_s")),
                     (m.get("loss_per_frame") or [None])[-1]))
    for row in sorted(rows, key=lambda x: (x[0], x[1], x[2])):
        lines.append("| " + " | ".join(fmt(v) for v in row) + " |")
    plt = plt_setup()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for enc in sorted({x[0] for x in rows}):
        sel = [x for x in rows if x[0] == enc]
        ax.scatter([x[5] for x in sel], [x[7] for x in sel], label=enc)
        for x in sel:
            ax.annotate(f"{x[1]}x{x[2]}", (x[5], x[7]), fontsize=7)
    ax.set_xlabel("training time per frame (s)")
    ax.set_ylabel(f"loss after {n_frames} frames")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    fig.savefig(images / "encodings.png", dpi=110)
    plt.close(fig)
    return lines + ["", "![encodings](../images/results/encodings.png)", ""]


def _loss_curves(runs, key: str, path: Path, title: str) -> None:
    plt = plt_setup()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for r in runs:
        loss = r["metrics"].get("loss_per_frame") or []
        ax.plot(range(len(loss)), loss, "-o", ms=3, label=r["choices"].get(key, "?"))
    ax.set_xlabel("frame")
    ax.set_ylabel("training loss (mean over the frame's batches)")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report_extra_inputs(root: Path, images: Path) -> list[str]:
    runs = load_runs(root, "extra_inputs")
    lines = header("Extra inputs: loss over frames (Fedotov Fig. 6.1/6.3)", ["extra_inputs"], root,
                   "Training loss per frame with the extra inputs none / density / gradient / laplacian "
                   "(default encoding, one run each: the curves carry Monte Carlo noise of one run).")
    if not runs:
        return lines + ["(no runs found)", ""]
    lines += ["| extra inputs | loss frame 0 | loss, mean of the last 3 frames | training (s/frame) | frame (s) |",
              "|---|---:|---:|---:|---:|"]
    for r in runs:
        m = r["metrics"]
        loss = m.get("loss_per_frame") or []
        lines.append(f"| {r['choices'].get('extra_inputs')} | {fmt(loss[0] if loss else None)} | "
                     f"{fmt(float(np.mean(loss[-3:])) if loss else None)} | "
                     f"{fmt(mean_after_first(m.get('time_train_s')))} | {fmt(mean_after_first(m.get('frame_times_s')))} |")
    _loss_curves(runs, "extra_inputs", images / "extra_inputs.png", "extra inputs")
    return lines + ["", "![extra inputs](../images/results/extra_inputs.png)", ""]


def report_batch_filters(root: Path, images: Path) -> list[str]:
    runs = load_runs(root, "batch_filters")
    lines = header("Training-batch filters x camera framing (Fedotov Table 6.1)", ["batch_filters"], root,
                   "Training time per frame (s, mean over frames 1..N-1) per filter; framings: `full` (whole "
                   "cloud), `close` (cloud fills the frame), `edge` (cloud at the frame's edge), `empty` (no "
                   "cloud in view). Medium pixels: share of pixels whose camera ray has transmittance < 0.999.")
    if not runs:
        return lines + ["(no runs found)", ""]
    framings = ["full", "close", "edge", "empty"]
    filters = ["none", "stripes", "quadtree"]
    table: dict[tuple[str, str], dict[str, Any]] = {}
    for r in runs:
        fr = str(r["cfg"].get("framing", "?"))
        table[(r["choices"].get("batch_filter"), fr)] = r["metrics"]
    lines += ["| filter | " + " | ".join(framings) + " |", "|---|" + "---:|" * len(framings)]
    for f in filters:
        cells = [fmt(mean_after_first(table.get((f, fr), {}).get("time_train_s"))) for fr in framings]
        lines.append(f"| {f} | " + " | ".join(cells) + " |")
    lines += ["", "Whole frame (s, mean over frames 1..N-1):", "",
              "| filter | " + " | ".join(framings) + " |", "|---|" + "---:|" * len(framings)]
    for f in filters:
        cells = [fmt(mean_after_first(table.get((f, fr), {}).get("frame_times_s"))) for fr in framings]
        lines.append(f"| {f} | " + " | ".join(cells) + " |")
    return lines + [""]


def _error_rows(runs, group_key) -> list[dict[str, Any]]:
    """Group runs (independent seeds) by ``group_key(run)``; metrics against the scene's reference."""
    groups: dict[Any, list] = {}
    for r in runs:
        groups.setdefault(group_key(r), []).append(r)
    out = []
    for key, rs in groups.items():
        ref_path = find_reference(rs[0]["cfg"])
        row: dict[str, Any] = {"key": key, "runs": len(rs), "reference": ref_path}
        times = []
        for r in rs:
            m = r["metrics"]
            t = mean_after_first(m.get("frame_times_s")) if m.get("frame_times_s") else m.get("time_render_s")
            times.append(t)
        row["time_s"] = float(np.mean([t for t in times if t is not None])) if any(times) else None
        if ref_path is not None:
            ref = read_reference(ref_path)
            xs = np.stack([read_exr(r["image"])[0] for r in rs])
            mask = medium_mask(ref.alpha) if ref.alpha is not None else None
            row["report"] = error_report(xs, ref.image, mask if mask is not None and mask.any() else None)
            row["floor"] = ref.rel_mse_floor_medium
            row["ref_spp"] = ref.attrs.get("spp")
        out.append(row)
    return out


def report_transmittance(root: Path, images: Path) -> list[str]:
    pt_runs, nrc_runs = load_runs(root, "transmittance_pt"), load_runs(root, "transmittance_nrc")
    lines = header("Transmittance estimators (Fedotov Fig. 6.16/6.17)", REPORTS["transmittance"], root,
                   "Path tracer at 1 spp: relMSE (mean over seeds), mean relative bias of the per-pixel mean "
                   "over seeds and relative variance across seeds, over the medium pixels; time per frame. "
                   "NRC: training loss of the last frame and time per frame (trace = render + training "
                   "paths, where the shadow rays are).")
    pt = {r["key"]: r for r in _error_rows(pt_runs, lambda r: r["choices"].get("transmittance"))}
    nrc = {r["choices"].get("transmittance"): r["metrics"] for r in nrc_runs}
    names = ["ratio", "residual_ratio", "track_length", "unbiased_raymarch", "biased_raymarch"]
    lines += ["| estimator | PT relMSE | PT rel. bias | PT rel. variance | PT time/frame (s) | seeds | "
              "NRC loss (last frame) | NRC trace (s/frame) | NRC frame (s) |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    floor = None
    for n in names:
        p = pt.get(n, {})
        med = (p.get("report") or {}).get("medium") or {}
        floor = p.get("floor", floor)
        m = nrc.get(n, {})
        lines.append(f"| {n} | {fmt(med.get('rel_mse'))} | {fmt(med.get('mean_relative_bias'))} | "
                     f"{fmt(med.get('relative_variance'))} | {fmt(p.get('time_s'))} | {p.get('runs', '–')} | "
                     f"{fmt((m.get('loss_per_frame') or [None])[-1])} | {fmt(mean_after_first(m.get('time_trace_s')))} | "
                     f"{fmt(mean_after_first(m.get('frame_times_s')))} |")
    if floor:
        lines += ["", f"The reference's own noise contributes relMSE ~ {fmt(floor)} (medium pixels). The bias of "
                  "an unbiased estimator is not zero here: the mean over a few seeds still carries their noise "
                  "(sqrt(2/pi) sigma / sqrt(K)); compare the estimators with each other."]
    if nrc_runs:
        _loss_curves(nrc_runs, "transmittance", images / "transmittance_nrc.png", "NRC loss per estimator")
        lines += ["", "![NRC loss per estimator](../images/results/transmittance_nrc.png)"]
    return lines + [""]


def report_nrc_vs_pt(root: Path, images: Path) -> list[str]:
    runs = load_runs(root, "nrc_vs_pt_pt") + load_runs(root, "nrc_vs_pt_nrc")
    lines = header("NRC vs PT at 1 spp (Spindler Fig. 5.8-5.10)", REPORTS["nrc_vs_pt"], root,
                   "Each row: independent runs (seeds) of one renderer on one setup; NRC shows its last frame "
                   "(1 spp) after on-line training. Recommended metrics (per-pixel, over the medium pixels): "
                   "MSE, relative MSE, mean relative bias |E[x]-r|/(r+0.01) with E over the seeds, relative "
                   "variance var_seeds(x)/(r^2+0.01). Thesis definitions (NOT recommended, for comparison "
                   "with their tables): rBias = |mean(x)-mean(r)|/mean(r), rVar = spatial var(x)/mean(r).")
    rows = _error_rows(runs, lambda r: (str(r["cfg"].get("setup", "?")), r["cfg"].renderer.name))
    lines += ["| setup | renderer | seeds | time/frame (s) | MSE | relMSE | rel. bias | rel. variance | "
              "thesis rBias | thesis rVar | reference spp |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in sorted(rows, key=lambda r: r["key"]):
        med = (r.get("report") or {}).get("medium") or {}
        lines.append(f"| {r['key'][0]} | {r['key'][1]} | {r['runs']} | {fmt(r['time_s'])} | {fmt(med.get('mse'))} | "
                     f"{fmt(med.get('rel_mse'))} | {fmt(med.get('mean_relative_bias'))} | "
                     f"{fmt(med.get('relative_variance'))} | {fmt(med.get('thesis_relative_bias'))} | "
                     f"{fmt(med.get('thesis_relative_variance'))} | {fmt(r.get('ref_spp'))} |")
    lines += ["", "Whole image (all pixels):", "",
              "| setup | renderer | MSE | relMSE | rel. bias | rel. variance | thesis rBias | thesis rVar |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in sorted(rows, key=lambda r: r["key"]):
        a = (r.get("report") or {}).get("all") or {}
        lines.append(f"| {r['key'][0]} | {r['key'][1]} | {fmt(a.get('mse'))} | {fmt(a.get('rel_mse'))} | "
                     f"{fmt(a.get('mean_relative_bias'))} | {fmt(a.get('relative_variance'))} | "
                     f"{fmt(a.get('thesis_relative_bias'))} | {fmt(a.get('thesis_relative_variance'))} |")
    return lines + [""]


BUILDERS = {
    "encodings": report_encodings, "extra_inputs": report_extra_inputs, "batch_filters": report_batch_filters,
    "transmittance": report_transmittance, "nrc_vs_pt": report_nrc_vs_pt,
}


# (label, run directory under docs/results/): first the comparison with the path tracer plus a denoiser on the
# scene types (the headline), then the earlier runs against the raw path tracer on the front-lit preset
SPEED_RUNS = [("side-lit Disney cloud (sun + sky, g 0.5), 480 x 270", "oidn_480x270_side_lit"),
              ("side-lit Disney cloud, 480 x 270, a warm cache", "oidn_480x270_side_lit_warm"),
              ("side-lit Disney cloud (sun + sky, g 0.5), 160 x 90", "oidn_160x90_side_lit"),
              ("side-lit Disney cloud, 160 x 90, a warm cache", "oidn_160x90_side_lit_warm"),
              ("the default cumulus (back-lit sun + sky, g 0.8), 160 x 90", "oidn_160x90_cumulus"),
              ("thin back-lit Disney cloud (density 0.15, g 0.95), 160 x 90", "oidn_160x90_back_lit_thin"),
              ("point light below the Disney cloud (g -0.3), 160 x 90", "oidn_160x90_point_below"),
              ("side-lit Disney cloud, 160 x 90, accumulated frames with a static camera",
               "oidn_160x90_side_lit_accumulate"),
              ("unbiased NRC (renderer.debias, q = 0.1, 0.25, 0.5) against the biased NRC and the path tracer: the "
               "side-lit Disney cloud, 160 x 90, accumulated 4-spp frames with a static camera",
               "debias_160x90_side_lit_accumulate"),
              ("light selection uniform against power: the side-lit Disney cloud, 160 x 90",
               "light_selection_160x90_side_lit"),
              ("light selection uniform against power: a point light below the Disney cloud with a dim sun and sky, "
               "160 x 90", "light_selection_160x90_three_lights"),
              ("light selection uniform, power and RIS (4 and 8 candidates): the many-lights preset (16 point lights "
               "below the cumulus, dim sky), 160 x 90, eager", "light_sampling_160x90_many_lights"),
              ("point lights by next-event estimation against equi-angular sampling: the lantern preset (a point light "
               "inside the cumulus), 80 x 45, eager", "light_sampling_80x45_lantern"),
              ("the lantern in a thinned cloud (density 0.1), 80 x 45, eager", "light_sampling_80x45_lantern_thin"),
              ("light selection uniform, power and RIS (4 candidates): the procedural cumulus under the thesis sun and "
               "a sky (scene=sun_sky), 160 x 90, eager", "light_sampling_160x90_sun_sky"),
              ("light selection uniform, power and RIS (4 candidates): the default scene (back-lit sun + sky), "
               "160 x 90, eager", "light_sampling_160x90_cumulus"),
              ("the path tracer and NRC with uniform and RIS light selection, raw and denoised: the many-lights preset, "
               "160 x 90, eager", "light_sampling_160x90_many_lights_nrc"),
              ("front-lit preset (sun_front), raw path tracer, 480 x 270 (older code)", "speed_480x270_v2"),
              ("front-lit preset (sun_front), raw path tracer, 160 x 90 (older code)", "speed_160x90_v2"),
              ("front-lit preset, 160 x 90, the default sweep (encodings, extra inputs, transmittance estimators; "
               "older code)", "speed_160x90_sweep_v2"),
              ("front-lit preset, 160 x 90, accumulated frames with a static camera (2 threads; older code)",
               "speed_160x90_accumulate_crossover"),
              ("front-lit preset, 80 x 45, accumulated frames with a static camera (older code)",
               "speed_80x45_accumulate_crossover")]
HEADLINE = "nrc"  # the NRC configuration of the headline runs (its denoised twin is nrc+oidn)
HEADLINE_RUNS = ("oidn_480x270_side_lit", "oidn_160x90_side_lit")  # the first one present is the headline


def _ratio(summary: dict, config: str, baseline: str) -> dict | None:
    for q in summary.get("equal_time", []):
        if q["config"] == config and q.get("baseline", "pt") == baseline and q.get("ratio_rel_mse_medium"):
            return q
    return None


def _row(summary: dict, config: str) -> dict | None:
    return next((r for r in summary.get("rows", []) if r["config"] == config and r["mode"] == "single"), None)


def scene_type_table(summaries: dict[str, tuple[str, dict]]) -> list[str]:
    """One row per run against the path tracer plus a denoiser (``oidn_*``): the equal-time relMSE ratios over
    the medium pixels raw and denoised, the image means, HDR-FLIP, and the earlier NRC defaults (``nrc_v1``)."""
    lines = ["| run | NRC / pt | NRC+OIDN / pt+OIDN | NRC / pt+OIDN | NRC+OIDN mean / ref | pt+OIDN mean / ref "
             "(nearest time) | HDR-FLIP NRC+OIDN / pt+OIDN | earlier defaults (`nrc_v1`): NRC+OIDN / pt+OIDN, mean |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, (label, summ) in summaries.items():
        den = _ratio(summ, HEADLINE + "+oidn", "pt+oidn")
        if not name.startswith("oidn_") or den is None:
            continue
        raw, cross = _ratio(summ, HEADLINE, "pt"), _ratio(summ, HEADLINE, "pt+oidn")
        old, row_old = _ratio(summ, "nrc_v1+oidn", "pt+oidn"), _row(summ, "nrc_v1+oidn")
        row = _row(summ, HEADLINE + "+oidn")
        pts = [r for r in summ["rows"] if r["mode"] == "single" and r.get("denoised") and r["renderer"] == "pt"]
        near = min(pts, key=lambda r: abs(r["time_s"] - den["time_s"])) if pts else {}
        warm = summ["meta"].get("argv", [])
        warmup = warm[warm.index("--warmup") + 1] if "--warmup" in warm else "?"
        lines.append(
            f"| {label}, {warmup} warm-up frames | {fmt(raw and raw['ratio_rel_mse_medium'], 2)} | "
            f"**{den['ratio_rel_mse_medium']:.2g}** | {fmt(cross and cross['ratio_rel_mse_medium'], 2)} | "
            f"{fmt(row.get('mean_ratio_medium'), 3)} | {fmt(near.get('mean_ratio_medium'), 3)} | "
            f"{fmt(row.get('flip'), 3)} / {fmt(near.get('flip'), 3)} | "
            + (f"{old['ratio_rel_mse_medium']:.2g}, {fmt(row_old.get('mean_ratio_medium'), 3)} |" if old and row_old
               else "– |"))
    return lines + [""] if len(lines) > 2 else []


def headline(summaries: dict[str, tuple[str, dict]]) -> list[str]:
    """The headline paragraph: NRC + OIDN against the path tracer + OIDN at equal time on the side-lit scene, the
    bias beside it, and the same ratio on every other scene type measured."""
    name = next((n for n in HEADLINE_RUNS if n in summaries), None)
    if name is None:
        return []
    label, summ = summaries[name]
    den, raw = _ratio(summ, HEADLINE + "+oidn", "pt+oidn"), _ratio(summ, HEADLINE, "pt")
    row_den = _row(summ, HEADLINE + "+oidn")
    if den is None or row_den is None:
        return []
    pts = [r for r in summ["rows"] if r["mode"] == "single" and r.get("denoised") and r["renderer"] == "pt"]
    row_pt = min(pts, key=lambda r: abs(r["time_s"] - den["time_s"])) if pts else None
    text = (f"**Headline ({label}; single frames at equal time per frame, over the medium pixels).** NRC + OIDN "
            f"against the path tracer + OIDN: relMSE ratio **{den['ratio_rel_mse_medium']:.2g}** "
            f"(NRC + OIDN {fmt(den['ratio_rel_mse_medium'] * den['pt_rel_mse_medium'])} at "
            f"{den['time_s']:.3g} s a frame, the path tracer + OIDN {fmt(den['pt_rel_mse_medium'])} in that time); "
            f"NRC + OIDN's image mean is **{fmt(row_den.get('mean_ratio_medium'), 3)}** of the reference's")
    if row_pt is not None:
        text += f" (the path tracer + OIDN's nearest-in-time frame: {fmt(row_pt.get('mean_ratio_medium'), 3)})"
    if raw is not None:
        text += f"; raw NRC against the raw path tracer: {raw['ratio_rel_mse_medium']:.2g}"
    others = []
    for n, (lab, sm) in summaries.items():
        q, r = _ratio(sm, HEADLINE + "+oidn", "pt+oidn"), _row(sm, HEADLINE + "+oidn")
        if n != name and n.startswith("oidn_") and q is not None and r is not None:
            others.append(f"{lab}: {q['ratio_rel_mse_medium']:.2g} (mean {fmt(r.get('mean_ratio_medium'), 3)})")
    if others:
        text += ". The same ratio on the other runs: " + "; ".join(others)
    return [text + ". A ratio above 1 means the path tracer plus a denoiser is better at equal time.", ""]


def _speed_section(docs: Path, label: str, name: str) -> tuple[list[str], dict | None]:
    d = docs / "results" / name
    if not (d / "summary.json").is_file():
        return [f"### {label}", "", f"(not run: `docs/results/{name}/summary.json` is missing)", ""], None
    summary = json.loads((d / "summary.json").read_text())
    meta = summary["meta"]
    argv = " ".join(meta.get("argv") or [])
    lines = [f"### {label}", "",
             f"Command (repo root): `python scripts/speed_vs_error.py {argv}` — took {meta['wall_time_s']:.0f} s. "
             f"Files: [`CSV`](results/{name}/speed_vs_error.csv), [`summary.json`](results/{name}/summary.json).", "",
             (d / "speed_vs_error.md").read_text(), "", f"![speed vs error {label}](results/{name}/speed_vs_error.png)", ""]
    return lines, summary


def assemble_results(docs: Path, intro: Path | None) -> Path:
    """``docs/results.md``: the intro (a hand-written Markdown file, optional), the speed-versus-error runs and
    the experiment reports, in that order."""
    lines = ["# Results", "",
             "Generated by `python scripts/experiments_report.py --results` from the outputs of "
             "`scripts/speed_vs_error.py` (under `docs/results/speed_*`) and the experiment multiruns "
             "(`conf/experiment/`). Every section names the command that reproduces it and the time it took.", ""]
    if intro is not None and intro.is_file():
        lines += [intro.read_text(), ""]
    lines += ["## Speed versus error", ""]
    summaries: dict[str, tuple[str, dict]] = {}
    for label, name in SPEED_RUNS:
        sec, summary = _speed_section(docs, label, name)
        lines += sec
        if summary is not None:
            summaries[name] = (label, summary)
    head = headline(summaries) + scene_type_table(summaries)
    if head:  # first thing on the page, after the line that says how it was generated
        lines[4:4] = head
    lines += ["## Thesis experiments at CPU scale", ""]
    for name in REPORTS:
        f = docs / "results" / f"{name}.md"
        lines += [f.read_text().replace("../images/results/", "images/results/") if f.is_file()
                  else f"### {name}\n\n(not run)", ""]
    out = docs / "results.md"
    out.write_text("\n".join(lines))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("reports", nargs="*", default=list(REPORTS), help=f"any of {', '.join(REPORTS)}")
    p.add_argument("--root", type=Path, default=REPO / "multirun" / "experiments")
    p.add_argument("--docs", type=Path, default=REPO / "docs")
    p.add_argument("--results", action="store_true", help="also assemble docs/results.md")
    p.add_argument("--intro", type=Path, default=REPO / "docs" / "results_intro.md",
                   help="hand-written Markdown placed at the top of results.md (if it exists)")
    p.add_argument("--conditions", default=CONDITIONS["text"],
                   help="how the multiruns were run (threads, other jobs), stated with each report")
    args = p.parse_args(argv)
    CONDITIONS["text"] = args.conditions
    out_md, out_img = args.docs / "results", args.docs / "images" / "results"
    out_md.mkdir(parents=True, exist_ok=True)
    out_img.mkdir(parents=True, exist_ok=True)
    for name in args.reports:
        if name not in BUILDERS:
            raise SystemExit(f"experiments_report: unknown report {name!r}; known: {', '.join(REPORTS)}")
        text = "\n".join(BUILDERS[name](args.root, out_img))
        (out_md / f"{name}.md").write_text(text)
        print(f"wrote {out_md / (name + '.md')}")
    if args.results:
        print(f"wrote {assemble_results(args.docs, args.intro)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
