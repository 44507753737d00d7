"""Speed versus error: the path tracer and NRC configurations on one scene and machine, in one invocation.

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

**As jobs** (``--jobs local|slurm``): each configuration runs as its own submitit job (:mod:`nrc.evaluation.jobs`)
writing its rows to ``<out>/configs/<NAME>.json``; the parent merges them into the same outputs, refusing rows
from different machine types.

The reference is ``--reference`` or ``data/references/reference_<scene hash>_<spp>spp.exr``, rendered
(resumably) with ``--ref-spp`` spp when missing; its own noise (``rel_mse_floor`` in its header) is
reported next to every relMSE, since each measured relMSE contains it.

Default scene (``--preset disney``): the ``sun`` preset with the shared Disney cloud
(``../shared/data/wdas_cloud_sixteenth.vdb`` relative to the repo root), ``density_scale 0.6``,
160 x 90 pixels; Hydra overrides after the options change it. Example::

    python scripts/speed_vs_error.py --out docs/results/speed_160x90
    python scripts/speed_vs_error.py --out docs/results/speed_480x270 scene.camera.width=480 \\
        scene.camera.height=270 --ref-spp 256 --configs pt,nrc_hashgrid
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]  # the checkout (data/references, outputs/ and git live there)

from nrc.config import CONF_DIR, code_version, compose, resolve_device  # noqa: E402
from nrc.io.atomic import write_text_atomically  # noqa: E402
from nrc.metrics import (flicker, hdr_flip, mean_ratio, mean_relative_bias, medium_mask, mse,  # noqa: E402
                                   normalised_rel_mse, rel_mse, relative_variance)
from nrc.evaluation.reference import (REF_SEED, check_independent, default_reference_path, read_reference,  # noqa: E402
                                     render_reference)
from nrc.scene import load_scene  # noqa: E402

# The scene types of the scripts are the files of conf/scene/ (``--preset side_lit`` is ``scene=side_lit``; the
# Disney cloud's ones read ../shared/data relative to the repo root, where the scripts run); ``none`` adds nothing.
PRESETS: tuple[str, ...] = (*sorted(p.stem for p in (Path(CONF_DIR) / "scene").glob("*.yaml") if p.stem != "base"),
                            "none")
PRESET_SIZES = {"lantern": ["scene.camera.width=80", "scene.camera.height=45"]}  # the size its runs were measured at


def preset(name: str) -> list[str]:
    """The overrides of the scene type ``name`` (one of :data:`PRESETS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown scene type {name!r}: one of {', '.join(PRESETS)}")
    return [] if name == "none" else [f"scene={name}", *PRESET_SIZES.get(name, [])]


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
SEED_BASE = 1000  # seeds of the scored renders; references use seeds >= 1e6 (nrc.evaluation.reference.REF_SEED)
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


def with_spp_seed(scene, spp: int, seed: int):
    return dataclasses.replace(scene, integrator=dataclasses.replace(scene.integrator, spp=int(spp), seed=int(seed)))


def warmup_scene(scene):
    """``scene`` with a 16 x 9 camera, for the untimed warm-up renders."""
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=16, height=9))


def pt_warmup(scene, cfg) -> None:
    """One untimed 16 x 9, 1-spp render: first-use costs of the ops (and of a compiled backend, if chosen)."""
    pt_render(warmup_scene(scene), cfg, 1, SEED_BASE - 1)


CPU_TIMES: list[float] = []  # process CPU time of each pt_render call (all threads), read by the callers


def pt_render(scene, cfg, spp: int, seed: int) -> tuple[np.ndarray, float]:
    """A pt render and its wall time; its process CPU time is appended to :data:`CPU_TIMES`."""
    from nrc.render.pt import PathTracer

    cfg.scene.integrator.spp, cfg.scene.integrator.seed = int(spp), int(seed)
    t0, c0 = time.perf_counter(), time.process_time()
    image = PathTracer(with_spp_seed(scene, spp, seed), cfg).render(progress=False).image
    CPU_TIMES.append(time.process_time() - c0)
    return np.nan_to_num(image), time.perf_counter() - t0


def nrc_run(scene, cfg, spp: int, seed: int, frames: int, accumulate: bool,
            on_frame: Callable[[int, np.ndarray, np.ndarray, dict], None]) -> Any:
    """Run the NRC renderer for ``frames`` frames, calling ``on_frame(frame, image, accumulated, stats)``;
    returns its :class:`~nrc.render.result.RenderResult`."""
    from omegaconf import open_dict

    from nrc.render.radiance_caching import NRCRenderer

    with open_dict(cfg):
        cfg.frames = int(frames)
        cfg.renderer.accumulate = bool(accumulate)
        cfg.scene.integrator.spp, cfg.scene.integrator.seed = int(spp), int(seed)
    return NRCRenderer(with_spp_seed(scene, spp, seed), cfg).render(progress=False, on_frame=on_frame)


def nrc_warmup(scene, cfg) -> float:
    """One untimed 16 x 9, 1-frame NRC run (as :func:`pt_warmup`): the compile, or its load from the persistent
    cache, happens here, not in the first scored frame; returns its wall time (reported as ``startup_s``)."""
    t0 = time.perf_counter()
    nrc_run(warmup_scene(scene), cfg.copy(), 1, SEED_BASE - 1, 1, False, lambda *a: None)
    return time.perf_counter() - t0


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


DENOISED = "+oidn"  # suffix of a configuration's denoised twin


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


def all_crossovers(rows: list[dict[str, Any]], baseline: list[str] | None) -> list[dict[str, Any]]:
    """Accumulated crossovers against every baseline the rows allow (as :func:`all_ratios`): raw NRC against the
    raw path tracers; with denoised twins NRC + OIDN and raw NRC against the path tracers + OIDN."""
    if not baseline:
        return []
    raw = [r for r in rows if not r.get("denoised")]
    den = [r for r in rows if r.get("denoised")]
    out = [{**c, "baseline": "pt"} for c in crossovers(raw, baseline)]
    den_base = [b + DENOISED for b in baseline]
    if any(r["config"] in den_base and r["mode"] == "accumulate" for r in den):
        out += [{**c, "baseline": "pt" + DENOISED} for c in crossovers(den, den_base)]
        pt_den = [r for r in den if r["renderer"] == "pt"]
        out += [{**c, "baseline": "pt" + DENOISED}
                for c in crossovers(pt_den + [r for r in raw if r["renderer"] != "pt"], den_base)]
    return out


def all_ratios(rows: list[dict[str, Any]], baseline: list[str] | None, clock: str = "time_s") -> list[dict[str, Any]]:
    """Equal-time ratios against every baseline the rows allow: raw NRC against the raw path tracers; with
    denoised twins also raw NRC and NRC + OIDN against the path tracers + OIDN (each item's ``baseline``)."""
    if not baseline:
        return []
    raw = [r for r in rows if not r.get("denoised")]
    den = [r for r in rows if r.get("denoised")]
    den_base = [b + DENOISED for b in baseline]
    pt_den = [r for r in den if r["renderer"] == "pt"]
    nrc_raw = [r for r in raw if r["renderer"] != "pt"]
    out = []
    for mode in ("single", "accumulate"):
        out += [{**q, "baseline": "pt"} for q in equal_time_ratios(raw, baseline, clock, mode)]
        if any(r["config"] in den_base for r in den):
            out += [{**q, "baseline": "pt" + DENOISED} for q in equal_time_ratios(den, den_base, clock, mode)]
            out += [{**q, "baseline": "pt" + DENOISED}
                    for q in equal_time_ratios(pt_den + nrc_raw, den_base, clock, mode)]
    return out


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
def loglog_interp(t: float, ts: list[float], es: list[float]) -> float:
    """``e(t)`` on the curve ``(ts, es)``, linear in log-log.

    Beyond its last point: slope -1 (an unbiased renderer's error ~ 1/time). Before its first point: flat,
    the error of the fastest measured frame: a path tracer cannot render a full frame faster than with
    its smallest spp, and assuming it could (slope -1) would flatter any faster competitor.
    """
    order = np.argsort(ts)
    lt, le = np.log(np.asarray(ts)[order]), np.log(np.asarray(es)[order])
    x = math.log(t)
    if x <= lt[0]:
        return float(math.exp(le[0]))
    if x >= lt[-1]:
        return float(math.exp(le[-1] - (x - lt[-1])))
    return float(math.exp(np.interp(x, lt, le)))


def add_corrected(rows: list[dict[str, Any]], floor: float | None, floor_medium: float | None) -> None:
    """``rel_mse[_medium]_corr``: relMSE minus the reference's own noise floor (an unbiased estimate of the
    relMSE against the true image, up to the reference's noise in the denominators; may be <= 0 when the
    error is below the floor's resolution)."""
    for r in rows:
        for key, f in (("rel_mse", floor), ("rel_mse_medium", floor_medium)):
            r[key + "_corr"] = None if (r.get(key) is None or f is None) else r[key] - f


def pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The best error reachable within each time: the ``(time, error)`` points no faster point beats, then
    their lower convex hull in log-log coordinates.

    A wavefront path tracer's time per frame is nearly flat in spp at low spp (the longest paths set
    it), so more spp can take no longer, or even less time on a noisy machine; the front keeps the curve
    monotone. The hull drops points above the straight log-log line between their neighbours: a frame
    with an spp count between two measured ones reaches that line (error ~ 1/spp, time ~ spp), so such a
    point is not the best the path tracer can do at its time (e.g. a slow eager 1-spp frame between the
    compiled backend's 1- and 4-spp frames).
    """
    front: list[tuple[float, float]] = []
    for t, e in sorted(points):
        if not front or e < front[-1][1]:
            front.append((t, e))
    hull: list[tuple[float, float]] = []
    for p in front:
        while len(hull) >= 2:
            (ax, ay), (bx, by) = ((math.log(q[0]), math.log(q[1])) for q in hull[-2:])
            cx, cy = math.log(p[0]), math.log(p[1])
            if (bx - ax) * (cy - ay) - (by - ay) * (cx - ax) > 0:  # b below the line a-c: keep it
                break
            hull.pop()
        hull.append(p)
    return hull


def baseline_of(rows: list[dict[str, Any]]) -> list[str] | None:
    """Every raw path-tracer configuration among ``rows``: the baseline of a summary (None without any)."""
    return list(dict.fromkeys(r["config"] for r in rows if r["renderer"] == "pt" and not r.get("denoised"))) or None


def baseline_names(baseline: str | list[str] | None) -> list[str]:
    """The path-tracer configurations of a baseline (one name in summaries written before it was a list)."""
    return [] if baseline is None else [baseline] if isinstance(baseline, str) else list(baseline)


def baseline_error(points: list[tuple[float, float]], t: float) -> float:
    """The best error the baseline's measured ``(time, error)`` points reach at time ``t``: on their Pareto front
    (log-log); between the front's slowest point and the slowest measured point the front is flat (spending that
    time was measured not to help, e.g. a denoised path tracer that is no better at 16 spp than at 4); beyond every
    measured point it is extrapolated (:func:`loglog_interp`)."""
    front = pareto(points)
    if front[-1][0] < t <= max(p[0] for p in points):
        return front[-1][1]
    return loglog_interp(t, [f[0] for f in front], [f[1] for f in front])


def equal_time_ratios(rows: list[dict[str, Any]], baseline: str | list[str], clock: str = "time_s",
                      mode: str = "single") -> list[dict[str, Any]]:
    """NRC single-frame points against the baseline path tracers at the same time per frame: the Pareto front of
    all their points (the best path-tracer error measured at that time, whichever configuration reached it).
    Between the front's slowest point and the slowest measured point the front is flat (spending that time was
    measured not to help); beyond every measured point it is extrapolated (:func:`loglog_interp`).

    ``clock``: ``time_s`` (wall time) or ``cpu_s`` (process CPU time, all threads: less sensitive to other
    jobs on a shared machine). ``mode="accumulate"``: the running means of a static camera at equal cumulative
    time instead (the path tracers' accumulated points against each NRC point; with ``--acc-startup`` both
    times count their start-up: the cold-start comparison).
    """
    if clock != "time_s":
        sel = [r for r in rows if r.get(clock) is not None]
        return equal_time_ratios([{**r, "time_s": r[clock]} for r in sel], baseline, mode=mode) if sel else []
    names = baseline_names(baseline)
    base = [r for r in rows if r["mode"] == mode and r["config"] in names]
    out = []
    if len(base) == 0:
        return out
    for r in rows:
        if r["mode"] != mode or r["renderer"] == "pt":
            continue
        item = {"config": r["config"], "mode": mode, "spp": r["spp"], "frames": r.get("frames", 1), "time_s": r["time_s"]}
        for key in ("rel_mse", "rel_mse_medium", "rel_mse_corr", "rel_mse_medium_corr"):
            if r.get(key) is None or any(b.get(key) is None or b[key] <= 0 for b in base) or r[key] <= 0:
                continue
            pt_e = baseline_error([(b["time_s"], b[key]) for b in base], r["time_s"])
            item[f"pt_{key}"] = pt_e
            item[f"ratio_{key}"] = r[key] / pt_e
            item["extrapolated"] = not (min(b["time_s"] for b in base) <= r["time_s"] <= max(b["time_s"] for b in base))
        out.append(item)
    return out


def crossovers(rows: list[dict[str, Any]], baseline: str | list[str]) -> list[dict[str, Any]]:
    """For each NRC accumulate curve: the first measured time after which the baseline path tracers (their
    Pareto front) are more accurate."""
    key = "rel_mse_medium" if any(r.get("rel_mse_medium") is not None for r in rows) else "rel_mse"
    names = baseline_names(baseline)
    base = [r for r in rows if r["mode"] == "accumulate" and r["config"] in names]
    out = []
    if not base:
        return out
    front = pareto([(b["time_s"], b[key]) for b in base])
    bt, be = [f[0] for f in front], [f[1] for f in front]
    for name in dict.fromkeys(r["config"] for r in rows if r["mode"] == "accumulate" and r["renderer"] != "pt"):
        curve = sorted((r for r in rows if r["mode"] == "accumulate" and r["config"] == name),
                       key=lambda r: r["time_s"])
        # Compared only where pt has a measurement (from its first frame on): before that it has no image.
        comparable = [r for r in curve if r["time_s"] >= bt[0]]
        # pt interpolated on the NRC times: a crossover is a sign change of log(pt/nrc)
        diff = [math.log(loglog_interp(r["time_s"], bt, be) / r[key]) for r in comparable]
        t_cross, before_first = None, False
        for i in range(len(comparable)):
            if diff[i] < 0 and all(d < 0 for d in diff[i:]):
                if i == 0:  # pt is already ahead at its first frame: the crossover is no later than that
                    t_cross, before_first = bt[0], True
                else:  # linear in log time between the last NRC-better and first pt-better points
                    a, b = diff[i - 1], diff[i]
                    la, lb = math.log(comparable[i - 1]["time_s"]), math.log(comparable[i]["time_s"])
                    t_cross = math.exp(la + (lb - la) * a / (a - b))
                break
        out.append({"config": name, "metric": key, "crossover_time_s": t_cross,
                    "crossover_at_or_before": before_first, "pt_first_time_s": bt[0],
                    "max_time_s": curve[-1]["time_s"] if curve else None,
                    "pt_better_at_end": bool(diff and diff[-1] < 0)})
    return out


# ---------------------------------------------------------------------------- outputs
def fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


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
    from omegaconf import open_dict

    path = args.reference or default_reference_path(cfg, args.ref_spp)
    if not args.reference and not path.is_file():
        log(f"rendering the reference {path} ({args.ref_spp} spp)")
        ref_cfg = compose(args.scene_overrides + ["renderer=pt", "transmittance=ratio", "renderer.backend=compiled"])
        with open_dict(ref_cfg):
            ref_cfg.scene.integrator.seed = REF_SEED
        render_reference(ref_cfg, path, min(args.ref_chunk, args.ref_spp), args.ref_spp, progress=args.progress)
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
            "reference": str(ref_path.relative_to(REPO) if ref_path.is_relative_to(REPO) else ref_path),
            "ref_spp": ref.attrs.get("spp"), "rel_mse_floor": ref.rel_mse_floor,
            "rel_mse_floor_medium": ref.rel_mse_floor_medium, "medium_pixels": int(mask.sum()),
            "baseline": baseline, "skipped": skipped, "nrc_overrides": args.nrc_overrides,
            "git": code_version(), "argv": argv,
            "machine": f"{platform.machine()}, {_cpu_count()} cores, torch {torch.__version__} "
                       f"({torch.get_num_threads()} threads)",
            "machine_type": machine_type(), "node": platform.node(), "threads": torch.get_num_threads(),
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


def _without_jobs(argv: list[str]) -> list[str]:
    """``argv`` without ``--jobs`` / ``--slurm`` and their values."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a in ("--jobs", "--slurm"):
            skip = True
        elif not a.startswith(("--jobs=", "--slurm=")):
            out.append(a)
    return out


def run_as_jobs(args: Any, argv: list[str], configs: dict[str, list[str]], base_cfg, log) -> int:
    """``--jobs local|slurm``: each configuration as its own launcher job (:mod:`nrc.evaluation.jobs`), which
    writes its rows to :func:`part_path`; then the tables, ratios and plot of the rows together, as one process
    would write them, refusing rows from different machine types. A configuration whose rows exist is not run
    again (delete them to re-measure). The reference is rendered first, here (``local``), or must exist
    (``slurm``: ``python -m nrc.reference_app``, docs/references.md)."""
    from nrc.evaluation.jobs import check_one_machine_type, run_commands

    start = time.perf_counter()
    path = args.reference or default_reference_path(base_cfg, args.ref_spp)
    if args.jobs == "slurm" and not path.is_file():
        raise SystemExit(f"speed_vs_error: no reference {path}: render it first, e.g. python -m nrc.reference_app "
                         f"{' '.join(args.scene_overrides)} scene.integrator.spp={args.ref_spp} (docs/references.md)")
    ref_path, ref = get_reference(base_cfg, args, log)
    script = REPO / "scripts" / "speed_vs_error.py"
    todo = {name: [sys.executable, str(script), *_without_jobs(argv), "--only", name]
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
    meta["reference"] = str(ref_path.relative_to(REPO) if ref_path.is_relative_to(REPO) else ref_path)
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


def _cpu_count() -> int:
    import os

    return os.cpu_count() or 0


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_type() -> str:
    """What equal-time ratios depend on: the CPU model, its core count, the threads and the torch version (results
    from machines of one type may be merged; a node's name is not part of it)."""
    return f"{cpu_model()}, {_cpu_count()} cores, {torch.get_num_threads()} threads, torch {torch.__version__}"

