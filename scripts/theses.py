"""The experiments of the two NRC-for-clouds theses (Fedotov 2024 "F", Spindler 2022 "S"), re-run at their own
settings, each scored on the image and given a verdict against the thesis's numbers.

The map of the experiments is ``../shared/THESES.md`` (section 2, numbered 1-17); :data:`EXPERIMENTS` holds one
entry per experiment id: the thesis's numbers and claims as data (paraphrased; lines cited as ``F:790``), the settings
config it runs at (``conf/experiment/thesis_{spindler,fedotov}.yaml``, every key citing its thesis line), what is
scaled for a CPU and why, its variants (name -> Hydra overrides on top of the config), how it is measured, and a
``verdict(data) -> (agrees | disagrees | not comparable, reason)``. Measurement kinds:

* ``curve`` -- per frame over ``runs`` runs from an untrained cache (seeds apart): the training loss, the image's
  relMSE over the medium pixels against a converged reference (its noise floor subtracted), the image mean over the
  reference's, the colour error (``chroma``: the largest over the smallest per-channel mean ratio, minus 1) and the
  flicker (mean ``|I_t - I_{t-1}|`` over the medium over the reference's mean); means with 95 % intervals; at the last
  frame the errors over the runs as independent renders (:func:`nrc.metrics.error_report`).
* ``nrc_vs_pt`` -- NRC's last frame (after ``frames`` frames) over ``runs`` seeds, and (unless ``pt`` is off) the path
  tracer at 1 spp over as many seeds, against the reference: MSE, the thesis's relative bias
  ``(mean(x) - mean(r)) / mean(r)`` and relative variance ``var(x) / mean(r)`` of one image (ALGORITHMS.md: the
  code's definitions), beside per-pixel statistics over the seeds (signed relative bias
  ``mean_px (mean_k x_k - r) / (|r| + 0.01)``, relative variance ``mean_px var_k(x_k) / (r^2 + 0.01)``).
* ``timing`` -- the renderer's per-pass times (``time_trace_s``, ``time_infer_s``, ``time_train_s``, the rest of the
  frame) and the training batches of each frame, averaged over ``frames`` frames after ``warm`` warm-up frames.
* ``cache`` -- a direct micro-benchmark of the cache (``nrc.cache.build_radiance_cache``): an inference pass of
  ``n_infer`` points and ``k`` training steps of a batch size, medians over ``repeats``.

Absolute times are the CPU's: a GPU time of the theses is "not comparable"; their verdicts compare ratios and trends.
A disagreement runs the experiment's ``explain`` ladder: ordered steps from the thesis's settings towards our
defaults, each measured the same way, so the page names the step that changes the answer.

Writes ``docs/theses/<id>.{json,md}`` (and ``<id>.png`` for the experiments whose thesis shows a plot) and the index
``docs/theses/README.md``. An experiment whose json exists is not run again (``--force``). Usage::

    python scripts/theses.py [--only F-6.2,S-5.3.1] [--runs N] [--width W --height H --train T] [--force]
                             [--no-explain] [--threads N] [--jobs local]
    python scripts/theses.py --quick --only S-5.3.1    # a smoke test: 32x18, 2 runs, a few frames
    python scripts/theses.py --report                  # the pages again from the jsons, nothing run

Default scale: 64x36 frames, a 32x32 training image, each experiment's runs and frames (its page says which and
why); about 30 minutes for the set on 2 cores without the ladders (``--no-explain``), each ladder up to 3x its
experiment's time. A result of another scale (a ``--quick`` one) is measured again. On a machine another job keeps
busy, ``--threads 1``: two threads on two busy cores made a training step 35x slower.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from lab import REPO, repo_relative
from lab.analysis import ci95
from lab.jobs import run_commands, without_jobs
from lab.machine import machine
from lab.tables import fmt, pm

OUT = REPO / "docs" / "theses"
CHROMA_GONE = 0.05  # F-6.1c: the colour distortion is gone from the frame its chroma error stays below this
Verdict = tuple[str, str]
VERDICTS = ("agrees", "disagrees", "not comparable")

# scene setups of S (S:643, S:737-757): overrides on top of a thesis config
S0_025 = ["scene.volume.density_scale=0.25"]
S1 = ["scene=point", "scene.volume.source=vdb", "scene.volume.path=../shared/data/wdas_cloud_sixteenth.vdb",
      "scene.lights=[{type:point,position:[0.0,0.0,0.0],intensity:[900.0,850.0,800.0]}]"]  # a point light at the
# centre of the medium (S:643); its intensity is not stated: the point preset's
# camera views of F's Table 6.1 (F:806-817 shows them only as images): where the cloud lies on the screen decides what
# a filter trains, so each view is chosen for the batch counts F prints (a: fills the screen, b: small at the centre,
# c: over three quadrants, d: in one corner, none: no cloud)
VIEWS: dict[str, list[str]] = {
    "a": ["scene.camera.position=[0.0,-2.0,70.0]", "scene.camera.look_at=[0.0,-14.0,0.0]"],
    "b": ["scene.camera.position=[0.0,-2.0,300.0]", "scene.camera.look_at=[0.0,-14.0,0.0]"],
    "c": ["scene.camera.position=[0.0,-2.0,180.0]", "scene.camera.look_at=[40.0,-40.0,0.0]"],
    "d": ["scene.camera.position=[0.0,-2.0,330.0]", "scene.camera.look_at=[110.0,-70.0,0.0]"],
    "none": ["scene.camera.position=[0.0,-2.0,150.0]", "scene.camera.look_at=[0.0,-2.0,400.0]"],
}
FILTERS = {"none": ["batch_filter=none", "batch_filter.n_batches=4", "~batch_filter.depth"],
           "stripes": ["batch_filter=stripes", "batch_filter.n_stripes=4", "~batch_filter.depth"],
           "quadtree": []}  # thesis_fedotov: the 2-level quadtree (F:835)
NOT_HASH = ["~encoding.position.n_levels", "~encoding.position.lr", "~encoding.position.log2_hashmap_size",
            "~encoding.position.lazy"]
ENCODINGS = {"T2": ["encoding=triangle_oneblob", *NOT_HASH, "encoding.position.n_frequencies=2"],
             "T12": ["encoding=triangle_oneblob", *NOT_HASH],
             "F12": ["encoding=frequency_oneblob", *NOT_HASH],
             "MRHE8": ["encoding.position.n_levels=8"],
             "MRHE12": []}  # OB4 on the direction in each (S:702)
# from the thesis's settings towards our defaults (conf/cache/default.yaml, conf/renderer/nrc.yaml, ...), cumulative
LADDER_OURS: list[tuple[str, list[str]]] = [
    ("hash lr 3e-4, dense Adam (ours)", ["encoding.position.lr=3e-4", "encoding.position.lazy=false"]),
    ("EMA over the last half of the steps, a quarter while the MLP rate is held (ours)",
     ["cache.ema.window_fraction=0.5", "cache.ema.hold_window_fraction=auto"]),
    ("cache target indirect (ours)", ["renderer.cache_target=indirect"]),
    ("unbiased fraction auto (ours)", ["renderer.training.unbiased_fraction=auto"]),
    ("our loss (floor 1, clamp 20 x the prediction) and MLP rate (decaying to a fifth) (ours)",
     ["cache.loss.scale_floor=1.0", "cache.loss.relative_clamp=20.0", "cache.loss.clamp_to=prediction",
      "cache.optimizer.lr_final_fraction=auto", "cache.optimizer.lr_half_life=auto", "cache.optimizer.lr_hold=auto"]),
    ("termination P(continue) 0 (ours)", ["renderer.termination.p_continue=0.0"]),
    ("our network (5 hidden layers, weight decay 1e-6) and ring buffer (auto) (ours)",
     ["cache.network.n_hidden_layers=5", "cache.optimizer.weight_decay=1e-6", "renderer.training.ring_buffer=auto"]),
    ("our encoding (hash grid: 8 levels to the grid's resolution, table auto, OB16)",
     ["encoding=hashgrid_oneblob", "encoding.position.n_levels=8", "encoding.position.log2_hashmap_size=auto",
      "encoding.direction.n_bins=16"]),
    ("our light-depth input (the optical depth towards the key light, one-blob encoded) (ours)",
     ["extra_inputs=light_depth"]),
]


# ---------------------------------------------------------------------------- the pure parts
def chroma(image: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    """The colour error: the largest over the smallest per-channel mean ratio (over ``mask``) minus 1 (0: the
    image's colour is the reference's, whatever its brightness)."""
    ratios = image[mask].mean(0) / np.maximum(ref[mask].mean(0), 1e-12)
    lo = float(ratios.min())
    return float(ratios.max()) / lo - 1.0 if lo > 0 else math.inf


def settle_frame(frames: Sequence[int], values: Sequence[float | None], threshold: float) -> int | None:
    """The first of ``frames`` from which ``values`` stays <= ``threshold``; None when it never does."""
    found = None
    for f, v in zip(frames, values):
        if v is None or not v <= threshold:
            found = None
        elif found is None:
            found = f
    return found


def smooth(values: Sequence[float | None], window: int = 5) -> list[float | None]:
    """A centred running mean over ``window`` frames (the loss of one frame is noisy)."""
    x = [np.nan if v is None else float(v) for v in values]
    out: list[float | None] = []
    for i in range(len(x)):
        w = [v for v in x[max(0, i - window // 2): i + window // 2 + 1] if np.isfinite(v)]
        out.append(float(np.mean(w)) if w else None)
    return out


def reach_frame(frames: Sequence[int], values: Sequence[float | None], level: float) -> int | None:
    """The first of ``frames`` at which ``values`` is at or below ``level``."""
    return next((f for f, v in zip(frames, values) if v is not None and v <= level), None)


def series(data: dict, variant: str, key: str) -> tuple[list[int], list[float | None]]:
    """A curve's frames and the mean of ``key`` per frame, of ``variant``."""
    rows = data["variants"][variant]["rows"]
    return [r["frame"] for r in rows], [r.get(key) for r in rows]


def tail_mean(data: dict, variant: str, key: str, fraction: float = 1 / 3) -> float | None:
    """The mean of ``key`` over the last ``fraction`` of a curve's frames."""
    _, v = series(data, variant, key)
    v = [x for x in v[-max(1, int(len(v) * fraction)):] if x is not None]
    return float(np.mean(v)) if v else None


def hydra_value(v: Any) -> str:
    """``v`` in Hydra's override grammar (lists and dicts nested, strings quoted)."""
    if isinstance(v, dict):
        return "{" + ",".join(f"{k}:{hydra_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(hydra_value(x) for x in v) + "]"
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return "'" + v.replace("'", "\\'") + "'"
    return repr(v)


def scene_overrides(scene: dict, prefix: str = "scene") -> list[str]:
    """Overrides that rebuild the composed ``scene`` block on ``scene=base`` (a path tracer's scene from an NRC
    config: the reference and the 1-spp baseline see exactly NRC's scene)."""
    out = [f"{prefix}=base"] if prefix == "scene" else []
    for k, v in scene.items():
        if isinstance(v, dict):
            out += scene_overrides(v, f"{prefix}.{k}")
        else:
            out.append(f"{prefix}.{k}={hydra_value(v)}")
    return out


# ---------------------------------------------------------------------------- the verdicts
def v_extra_inputs(d: dict) -> Verdict:
    """F-6.1a: the three inputs give practically the same loss curves (F:779)."""
    tails = {v: tail_mean(d, v, "loss") for v in d["variants"]}
    vals = [x for x in tails.values() if x is not None]
    if len(vals) < 2:
        return "not comparable", "fewer than two loss curves"
    spread = max(vals) / min(vals) - 1
    nums = ", ".join(f"{k} {fmt(v)}" for k, v in tails.items())
    if spread <= 0.25:
        return "agrees", f"the late losses ({nums}) lie within {spread:.0%} of each other"
    return "disagrees", f"the late losses ({nums}) differ by {spread:.0%} (> 25 %)"


def density_speedup(d: dict, at: int = 25) -> tuple[float | None, int | None, bool]:
    """F-6.1b: the frame at which the loss without density (smoothed) reaches the loss with density at frame ``at``,
    over ``at``; (ratio or its lower bound, that frame, whether it was reached)."""
    f, with_d = series(d, "density", "loss")
    _, without = series(d, "none", "loss")
    at = at if f[-1] >= 4 * at else max(1, f[-1] // 4)  # a run too short for frame 25: a quarter of its frames
    level = smooth(with_d)[f.index(at)] if at in f else None
    if level is None:
        return None, None, False
    reached = reach_frame(f, smooth(without), level)
    return (reached / at if reached else f[-1] / at), reached, reached is not None


def v_density_speedup(d: dict) -> Verdict:
    ratio, frame, reached = density_speedup(d)
    f = series(d, "density", "loss")[0]
    at = f"at frame {25 if f[-1] >= 100 else max(1, f[-1] // 4)}: "
    if ratio is None:
        return "not comparable", "no loss at the comparison frame"
    if not reached:
        if ratio >= 3:
            return "agrees", at + "without density the loss never reaches the density run's within " \
                                  f"{d['frames']} frames (speed-up >= {ratio:.1f}x; F: 6x)"
        return "not comparable", at + f"not reached within {d['frames']} frames: the run is too short to tell " \
                                      f"(>= {ratio:.1f}x)"
    if ratio >= 3:
        return "agrees", at + f"the loss without density reaches the density run's at {ratio:.1f}x the frames (F: 6x)"
    return "disagrees", at + f"the loss without density reaches the density run's at {ratio:.1f}x the frames (F: 6x)"


def settle_frames(d: dict) -> dict[str, int | None]:
    return {v: settle_frame(*series(d, v, "chroma"), CHROMA_GONE) for v in d["variants"]}


def v_colour(d: dict) -> Verdict:
    """F-6.1c: with density the colour distortion is gone in half the frames (64 -> 32, F:675-681, F:793)."""
    s = settle_frames(d)
    a, b = s.get("none"), s.get("density")
    nums = f"colour error <= {CHROMA_GONE} from frame {fmt(a)} without density, {fmt(b)} with it"
    if b is None:
        return "disagrees", nums + " (never with density)"
    if a is None or b < a:
        return "agrees", nums
    return "disagrees", nums


def v_filters(d: dict) -> Verdict:
    """F-6.2: the quadtree never trains longer than stripes in a view with the cloud; neither trains without one
    (F:853-859; the view without a cloud is judged by its batch count, its times are ~0 either way)."""
    t = {k: v["time_train_s"] for k, v in d["variants"].items()}
    bad = [view for view in VIEWS if view != "none" and t.get(f"quadtree/{view}") is not None
           and t.get(f"stripes/{view}") is not None and t[f"quadtree/{view}"] > 1.15 * t[f"stripes/{view}"]]
    empty = [f for f in ("stripes", "quadtree") if (d["variants"].get(f"{f}/none") or {}).get("train_steps", 0) > 0]
    ratios = ", ".join(f"{v} {fmt(t[f'quadtree/{v}'] / t[f'none/{v}'], 2) if t.get(f'none/{v}') else '–'}"
                       for v in VIEWS if f"quadtree/{v}" in t)
    if bad or empty:
        return "disagrees", f"quadtree slower than stripes in {bad or 'no view'}; trains without a cloud: " \
                            f"{empty or 'none'} (quadtree/none train time: {ratios})"
    return "agrees", f"quadtree never slower than stripes (15 % noise allowed), nothing trained without a cloud; " \
                     f"quadtree/none train time per view: {ratios} (F: a 0.51, b 0.43, c 0.79, d 0.30)"


def few_large_ratio(d: dict) -> float | None:
    """Many small over few large: the time of 65,536 samples as the most batches over as one."""
    t = {int(k.split("x")[0]): v["train_s"] for k, v in d["variants"].items()}
    return t[max(t)] / t[min(t)] if t else None


def v_few_large(d: dict) -> Verdict:
    """F-4.2 / S Fig 5.6: a few large batches train faster than many small ones."""
    r = few_large_ratio(d)
    if r is None:
        return "not comparable", "no times"
    if r >= 1.2:
        return "agrees", f"the same samples in the most, smallest batches take {r:.2f}x the time of one batch " \
                         "(S Fig 5.6: 4x2^14 / 1x2^16 = 2.12)"
    return "disagrees", f"the most, smallest batches take {r:.2f}x one batch's time: on the CPU the cost is per " \
                        "sample, not per call (the GPU's launch and fill costs are what made few large batches pay)"


def nrc_pt_metric(d: dict, variant: str, side: str, key: str) -> float | None:
    return ((d["variants"].get(variant) or {}).get(side) or {}).get(key)


def v_estimators(d: dict) -> Verdict:
    """F-6.3a: both Kettunen estimators beat ratio tracking on relative variance and MSE; biased ~10.5 % lower
    relative variance and MSE than unbiased (F:883-885)."""
    m = {e: nrc_pt_metric(d, e, "nrc", "mse") for e in ("ratio", "unbiased", "biased")}
    rv = {e: nrc_pt_metric(d, e, "nrc", "relative_variance") for e in m}
    if None in m.values():
        return "not comparable", "missing estimators"
    nums = "MSE " + ", ".join(f"{k} {fmt(v)}" for k, v in m.items())
    beat = m["unbiased"] < m["ratio"] and m["biased"] < m["ratio"]
    if beat and m["biased"] <= m["unbiased"]:
        return "agrees", nums + f"; relative variance {', '.join(f'{k} {fmt(v)}' for k, v in rv.items())}"
    return "disagrees", nums + " (F: ratio worst, biased best)"


def v_loss_per_estimator(d: dict) -> Verdict:
    """F-6.3b: the biased estimator gives the lowest loss (F:887-890)."""
    tails = {v: tail_mean(d, v, "loss") for v in d["variants"]}
    if None in tails.values():
        return "not comparable", "missing loss curves"
    best = min(tails, key=lambda k: tails[k])
    nums = ", ".join(f"{k} {fmt(v)}" for k, v in tails.items())
    return ("agrees" if best == "biased" else "disagrees"), f"late mean loss {nums}; lowest: {best} (F: biased)"


def v_trace_time(d: dict) -> Verdict:
    """S Fig 5.4: the trace time rises with P(continue) and the minimum vertex count; scene 1 is cheaper."""
    t = {k: v["time_trace_s"] for k, v in d["variants"].items()}
    ps, mins = ("0.0", "0.25", "0.5", "0.75"), (1, 2, 3, 4)
    up_p = up_m = cheaper = total = 0
    for s in ("S0", "S1"):
        for m in mins:
            row = [t.get(f"{s}/p{p}/min{m}") for p in ps]
            up_p += all(a is not None and b is not None and b >= 0.95 * a for a, b in zip(row, row[1:]))
        for p in ps:
            col = [t.get(f"{s}/p{p}/min{m}") for m in mins]
            up_m += all(a is not None and b is not None and b >= 0.95 * a for a, b in zip(col, col[1:]))
    for p in ps:
        for m in mins:
            a, b = t.get(f"S0/p{p}/min{m}"), t.get(f"S1/p{p}/min{m}")
            if a is not None and b is not None:
                total += 1
                cheaper += b < a
    nums = f"rising in P(continue) in {up_p}/8 rows, in the minimum in {up_m}/8 columns; scene 1 cheaper in " \
           f"{cheaper}/{total} cells"
    if total and up_p >= 6 and up_m >= 6 and cheaper >= 0.75 * total:
        return "agrees", nums
    return "disagrees", nums + " (S: all rising, scene 1 2.6-4.2x cheaper)"


def v_passes(d: dict) -> Verdict:
    """S:677-681: preparing the training records (and filtering) costs a few per cent of the frame. Our passes are
    not S's: inference includes preparing the queries and the final image; the training pass's time besides its
    steps is the closest to Prepare-Train-Rays."""
    v = next(iter(d["variants"].values()))
    share = v["time_other_s"] / v["time_frame_s"] if v.get("time_frame_s") else None
    if share is None:
        return "not comparable", "no frame time"
    word = "agrees" if share <= 0.1 else "disagrees"
    return word, f"preparing the training records and batches is {share:.1%} of the frame (S: Prepare-Train-Rays " \
                 "0.36 of 32.2 ms, 1.1 %; all three small passes 1.25 ms, 3.9 %, derived)"


def v_encodings_time(d: dict) -> Verdict:
    """S Fig 5.5: the time rises with depth and width; the hash grid costs most, T2 least."""
    t = {k: v["total_s"] for k, v in d["variants"].items()}
    checks = []
    for enc in ENCODINGS:
        for w in (64, 128):
            col = [t.get(f"{enc}/{w}x{n}") for n in (3, 4, 5, 6)]
            if None not in col:
                checks.append(("depth", col[-1] > col[0]))
        for n in (3, 4, 5, 6):
            a, b = t.get(f"{enc}/64x{n}"), t.get(f"{enc}/128x{n}")
            if a is not None and b is not None:
                checks.append(("width", b > a))
    for w in (64, 128):
        for n in (3, 6):
            row = {e: t.get(f"{e}/{w}x{n}") for e in ENCODINGS}
            if None not in row.values():
                checks.append(("hash most", max(row, key=lambda e: row[e]) in ("MRHE12", "MRHE8")))
                checks.append(("T2 least", min(row, key=lambda e: row[e]) == "T2"))
    if not checks:
        return "not comparable", "no times"
    failed = sorted({name for name, ok in checks if not ok})
    held = sum(ok for _, ok in checks)
    if held >= 0.8 * len(checks):
        return "agrees", f"{held}/{len(checks)} orderings of S Fig 5.5 hold" + \
            (f" (not always: {failed})" if failed else "")
    return "disagrees", f"only {held}/{len(checks)} orderings hold; failing: {failed}"


def v_batch_time(d: dict) -> Verdict:
    """S Fig 5.6: near-linear in the batch count; few large batches beat many small ones."""
    t = {k: v["train_s"] for k, v in d["variants"].items()}
    sizes = sorted({int(k.split("x")[1].removeprefix("2^")) for k in t})
    counts = sorted({int(k.split("x")[0]) for k in t})
    if not sizes or len(counts) < 2:
        return "not comparable", "no times"
    lin = [t[f"{counts[-1]}x2^{s}"] / t[f"1x2^{s}"] for s in sizes]
    r = None
    if len(sizes) >= 3 and 4 in counts:
        r = t[f"4x2^{sizes[0]}"] / t[f"1x2^{sizes[2]}"]
    nums = f"{counts[-1]} batches / 1: {', '.join(f'{x:.1f}' for x in lin)} (S at 2^14: 4.9)"
    if r is not None:
        nums += f"; 4x2^{sizes[0]} / 1x2^{sizes[2]}: {r:.2f} (S: 2.12)"
    linear = all(0.5 * counts[-1] <= x <= 1.5 * counts[-1] for x in lin)
    if linear and (r is None or r >= 1.2):
        return "agrees", nums
    return "disagrees", nums + ("" if linear else "; not linear in the count") + \
        ("" if r is None or r >= 1.2 else "; few large batches do not pay on the CPU (cost per sample, not per call)")


def v_flicker(d: dict) -> Verdict:
    """S-5.3.1: the EMA (alpha 0.99) damps the flicker of lr 0.01."""
    a, b = tail_mean(d, "ema 0.99", "flicker", 0.5), tail_mean(d, "no EMA", "flicker", 0.5)
    if a is None or b is None:
        return "not comparable", "no flicker figures"
    nums = f"frame-to-frame change over the second half: {fmt(b)} without the EMA, {fmt(a)} with it"
    return ("agrees", nums) if b > 1.1 * a else ("disagrees", nums + " (S: visibly damped)")


def v_encodings_quality(d: dict) -> Verdict:
    """S-5.3.2: the hash grid's colour shift vanishes first; T and F have more bias than the hash grid."""
    s = settle_frames(d)
    out, fails = [], []
    for w in ("6x64", "3x64"):
        bias = {e: abs(((d["variants"].get(f"{e}/{w}") or {}).get("final") or {}).get("signed_relative_bias") or np.nan)
                for e in ("T12", "F12", "MRHE12")}
        sh = {e: s.get(f"{e}/{w}") for e in ("T12", "F12", "MRHE12")}
        out.append(f"{w}: |bias| " + ", ".join(f"{e} {fmt(v)}" for e, v in bias.items())
                   + "; colour settled at " + ", ".join(f"{e} {fmt(v)}" for e, v in sh.items()))
        if not bias["MRHE12"] <= min(bias["T12"], bias["F12"]):
            fails.append(f"{w} bias")
        never = 10 ** 9
        if (sh["MRHE12"] or never) > min(sh["T12"] or never, sh["F12"] or never):
            fails.append(f"{w} colour")
    return ("disagrees", "; ".join(out) + f" (failing: {fails})") if fails else ("agrees", "; ".join(out))


def v_nrc_vs_pt(expect: str) -> Callable[[dict], Verdict]:
    """S Ex1-3: ``less_noise`` (NRC's MSE and relative variance below PT's, NRC darker) or ``equal`` (MSE ratio
    within [0.7, 1.4])."""

    def verdict(d: dict) -> Verdict:
        v = next(iter(d["variants"]))
        m = {side: nrc_pt_metric(d, v, side, "mse") for side in ("nrc", "pt")}
        rv = {side: nrc_pt_metric(d, v, side, "relative_variance") for side in ("nrc", "pt")}
        b = nrc_pt_metric(d, v, "nrc", "thesis_signed_bias")
        if None in m.values() or not m["pt"]:
            return "not comparable", "missing errors"
        r = m["nrc"] / m["pt"]
        nums = f"NRC/PT MSE {r:.2f}, relative variance {fmt(rv['nrc'])} vs {fmt(rv['pt'])}, NRC bias {fmt(b)}"
        if expect == "equal":
            return ("agrees" if 0.7 <= r <= 1.4 else "disagrees"), nums + " (S: about equal, 1.06)"
        ok = r < 1 and rv["nrc"] is not None and rv["pt"] is not None and rv["nrc"] < rv["pt"] and -0.25 <= (b or 0) < 0
        return ("agrees" if ok else "disagrees"), nums + " (S: NRC less noisy, lower MSE, a small negative bias, " \
                                                         "-0.076 in Ex1; here at most -0.25 counts as small)"

    return verdict


def v_ring_buffer(d: dict) -> Verdict:
    """S-4.2: with the ring buffer the cache learns faster (visibly, depending on the camera)."""
    a, b = tail_mean(d, "ring buffer", "rel_mse", 2 / 3), tail_mean(d, "no ring buffer", "rel_mse", 2 / 3)
    if a is None or b is None:
        return "not comparable", "no curves"
    nums = f"mean relMSE over the last two thirds: {fmt(a)} with, {fmt(b)} without the ring buffer"
    return ("agrees", nums) if a < b else ("disagrees", nums + " (S: faster with it)")


# ---------------------------------------------------------------------------- the registry
@dataclasses.dataclass(frozen=True)
class Experiment:
    """One experiment of THESES.md section 2 (``number``: its number there)."""

    id: str
    number: int
    title: str
    source: str
    question: str
    thesis: dict[str, Any]  # {"claims": [...], "table": {"columns": [...], "rows": [[...], ...]}} paraphrased
    config: str  # conf/experiment/<config>.yaml
    kind: str  # curve | nrc_vs_pt | timing | cache
    variants: dict[str, list[str]]
    verdict: Callable[[dict], Verdict]
    scaled: str
    runs: int = 5
    frames: int = 30
    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    explain: list[tuple[str, list[str]]] = dataclasses.field(default_factory=list)
    plot: bool = False  # the thesis shows a plot: ours beside it
    reuse: str | None = None  # the id whose measurement this one reads (the same runs, another question)

    @property
    def subject(self) -> set[str]:
        """The config keys its variants set (what the experiment varies)."""
        return {o.split("=", 1)[0].lstrip("+~") for v in self.variants.values() for o in v}

    def ladder(self) -> list[tuple[str, list[str]]]:
        """The ``explain`` steps without the overrides of keys a variant sets (the variants are the experiment's
        :attr:`subject`: a step must not undo one, e.g. our ring buffer on S-4.2's 'no ring buffer'); empty steps
        dropped."""
        subject = self.subject
        steps = [(name, [o for o in ovs if o.split("=", 1)[0] not in subject]) for name, ovs in self.explain]
        return [(name, ovs) for name, ovs in steps if ovs]


SCALE = ("the frame 64x36 (the theses: 1920x1080) and the training image 32x32 paths x 4 records = 4 batches of "
         "2^10 (the theses: 4 of 2^14): at the theses' settings (6x64, 12 hash levels, P(continue) 0.5, frames "
         "waiting for their training paths) a CPU frame takes ~0.3 s even so")
SCALE_CURVE = SCALE + "; 10 runs as F (F:790)"
F_CURVE_RUNS = 10
_ext = {"density": ["extra_inputs=density"], "gradient": ["extra_inputs=gradient"],
        "laplacian": ["extra_inputs=laplacian"]}
EXPERIMENTS: list[Experiment] = [
    Experiment("F-6.1a", 1, "Which extra cloud input?", "F:779-786 (Fig 6.1)",
               "Which third input speeds up online training most: density, its gradient or its Laplacian?",
               {"claims": ["all three give practically the same loss curves, so density was kept (F:779)",
                           "no input is encoded; an encoding changed nothing (F:781)"]},
               "thesis_fedotov", "curve", _ext, v_extra_inputs, SCALE_CURVE + "; 30 frames", runs=F_CURVE_RUNS,
               frames=30,
               explain=LADDER_OURS, plot=True),
    Experiment("F-6.1b", 2, "Density input speed-up", "F:788-798 (Fig 6.3)",
               "How much faster does the training loss fall with the density input than with position and direction?",
               {"claims": ["the loss with density at frame 25 equals the loss without at frame 150: ~6x shorter "
                           "training (F:790, F:238, F:904)", "the input does not slow rendering (F:783)"],
                "table": {"columns": ["quantity", "value"], "rows": [["speed-up (frames)", 6.0]]}},
               "thesis_fedotov", "curve", {"none": ["extra_inputs=none"], "density": []}, v_density_speedup,
               SCALE_CURVE + "; 64 frames (F plots 150+): a speed-up beyond 64/25 shows as a lower bound",
               runs=F_CURVE_RUNS, frames=64, explain=LADDER_OURS, plot=True),
    Experiment("F-6.1c", 3, "Warm-up colour distortions", "F:675-681, F:783, F:793-794 (Figs 4.1, 6.2)",
               "After how many frames is the colour distortion of online training gone, with and without density?",
               {"claims": ["without density the distortion is invisible from frame 64; with density from about "
                           "frame 32 (visual, F:793-794)"],
                "table": {"columns": ["variant", "frames"], "rows": [["none", 64], ["density", 32]]}},
               "thesis_fedotov", "curve", {"none": ["extra_inputs=none"], "density": []}, v_colour,
               SCALE_CURVE + f"; visual inspection replaced by a measure: the frame from which the colour error "
               f"(max/min per-channel mean ratio - 1) stays <= {CHROMA_GONE}",
               runs=F_CURVE_RUNS, frames=64, explain=LADDER_OURS, plot=True, reuse="F-6.1b"),
    Experiment("F-6.2", 4, "Training-batch filtering", "F:800-868 (Table 6.1)",
               "What does training cost with no filter, 4 stripes and the 2-level quadtree in four views and none?",
               {"claims": ["the quadtree is never slower than stripes; neither trains without a cloud (F:853-859)"],
                "table": {"columns": ["view", "none ms (batches)", "stripes ms (batches)", "quadtree ms (batches)"],
                          "rows": [["a", "13.06 (4)", "12.91 (4)", "6.62 (1)"],
                                   ["b", "10.01 (4)", "5.32 (2 central)", "4.26 (1)"],
                                   ["c", "11.17 (4)", "8.89 (3)", "8.79 (3)"],
                                   ["d", "10.41 (4)", "6.09 (2)", "3.11 (1 corner)"],
                                   ["none", "9.62 (4)", "0.00 (0)", "0.00 (0)"]]}},
               "thesis_fedotov", "timing",
               {f"{f}/{v}": [*fo, *vo] for f, fo in FILTERS.items() for v, vo in VIEWS.items()}, v_filters,
               SCALE + "; 10 frames averaged after 2 warm-up frames (F: 100)", runs=1, frames=10,
               params={"warm": 2}),
    Experiment("F-4.2", 5, "Few large against many small training batches", "F:717, F:729, F:851",
               "Do the same training samples train faster as a few large batches than as many small ones?",
               {"claims": ["a few large batches train faster than many small ones (F:717, F:729)",
                           "derived from Table 6.1: 65,536 samples as 4 batches 13.06 / 10.01 ms, as one 6.62 / "
                           "4.26 ms"],
                "table": {"columns": ["split", "view a ms", "view b ms"], "rows": [["4 x 2^14", 13.06, 10.01],
                                                                                   ["1 x 2^16", 6.62, 4.26]]}},
               "thesis_fedotov", "cache",
               {f"{2 ** k}x2^{16 - k}": [] for k in (0, 1, 2, 3, 4)}, v_few_large,
               "none: 65,536 samples a frame as in F (F:819), the cache alone (no rendering)", runs=1,
               params={"repeats": 3, "split": True}),
    Experiment("F-6.3a", 6, "Transmittance estimators: quality and time", "F:870-885 (Fig 6.16)",
               "Inside NRC, how do ratio tracking, Kettunen's unbiased ray marching and its biased variant compare?",
               {"claims": ["both new estimators beat ratio tracking on every metric (F:883)",
                           "biased: about 10.5 % lower relative variance and MSE than unbiased, slightly more bias "
                           "(F:885)"]},
               "thesis_fedotov", "nrc_vs_pt",
               {"ratio": ["transmittance=ratio"], "unbiased": ["transmittance=unbiased_raymarch"],
                "biased": ["transmittance=biased_raymarch"]}, v_estimators,
               SCALE + "; 20 frames, the last frame scored over 5 seeds (F: 100 frames averaged); reference "
               "1024 spp of the path tracer (F: 8192 spp)", runs=5, frames=20, params={"pt": False},
               explain=LADDER_OURS, plot=True),
    Experiment("F-6.3b", 7, "Transmittance estimator and training loss", "F:887-890 (Fig 6.17)",
               "Which shadow-ray estimator gives the lowest training loss?",
               {"claims": ["the biased estimator gives the lowest loss; all reach their floor equally fast (F:890)"]},
               "thesis_fedotov", "curve",
               {"ratio": ["transmittance=ratio"], "unbiased": ["transmittance=unbiased_raymarch"],
                "biased": ["transmittance=biased_raymarch"]}, v_loss_per_estimator,
               SCALE_CURVE + "; 20 frames", runs=F_CURVE_RUNS, frames=20, explain=LADDER_OURS, plot=True),
    Experiment("S-5.2-Fig5.4", 8, "Generate-Rays pass time", "S:653-661, S:675 (Fig 5.4)",
               "How does the path-tracing pass cost scale with P(continue) and the minimum vertex count, scene 0 "
               "against scene 1?",
               {"claims": ["cost grows with the scattering events simulated; the point-light scene is 2.6-4.2x "
                           "cheaper (derived)"],
                "table": {"columns": ["P(continue)", "S0 min1", "S0 min2", "S0 min3", "S0 min4", "S1 min1", "S1 min2",
                                      "S1 min3", "S1 min4"],
                          "rows": [[0.0, 5.63, 14.36, 23.89, 35.04, 2.14, 3.61, 5.72, 8.63],
                                   [0.25, 10.12, 18.49, 27.51, 36.17, 3.38, 5.03, 7.31, 9.93],
                                   [0.5, 17.28, 25.03, 34.9, 42.78, 5.54, 7.79, 10.21, 13.22],
                                   [0.75, 36.07, 42.23, 50.16, 55.83, 11.78, 13.77, 16.57, 18.76]]}},
               "thesis_spindler", "timing",
               {f"{s}/p{p}/min{m}": [*so, f"renderer.termination.p_continue={p}",
                                     f"renderer.termination.min_vertices={m}"]
                for s, so in (("S0", []), ("S1", S1)) for p in ("0.0", "0.25", "0.5", "0.75") for m in (1, 2, 3, 4)},
               v_trace_time, SCALE + "; 5 frames averaged after 1 warm-up frame (not stated in S)", runs=1, frames=5,
               params={"warm": 1}, plot=True),
    Experiment("S-5.2-passes", 9, "The other pass times", "S:677-681",
               "What do the passes besides tracing, inference and training cost?",
               {"claims": ["Prepare-Infer-Rays <= 0.59 ms, Prepare-Train-Rays 0.36 ms, Rendering ~0.3 ms, "
                           "against 17.28 ms tracing and 13.68 ms inference + training (derived frame: 32.2 ms)"]},
               "thesis_spindler", "timing", {"comparison setup": []}, v_passes,
               SCALE + "; 20 frames after 2 warm-up frames", runs=1, frames=20, params={"warm": 2}),
    Experiment("S-5.2-Fig5.5", 10, "Inference + training time against encoding, width and depth",
               "S:663-671, S:685-704 (Fig 5.5)",
               "How does inference + training time grow with the encoding, the hidden width and the depth?",
               {"claims": ["cost rises with frequencies or levels, most steeply for the hash grid (S:704)",
                           "F costs 1.99 ms more than T at equal frequencies (S:704)"],
                "table": {"columns": ["layers", "T2 64", "T2 128", "T12 64", "T12 128", "F12 64", "F12 128",
                                      "MRHE8 64", "MRHE8 128", "MRHE12 64", "MRHE12 128"],
                          "rows": [[3, 4.95, 7.3, 5.87, 8.46, 7.02, 9.49, 8.67, 11.05, 11.37, 14.56],
                                   [4, 5.93, 8.74, 6.53, 10.52, 7.83, 11.8, 9.51, 12.87, 12.61, 16.15],
                                   [5, 6.73, 10.81, 7.55, 12.14, 10.64, 14.31, 10.64, 14.31, 12.94, 17.08],
                                   [6, 7.51, 12.36, 8.16, 13.77, 11.36, 16.47, 11.36, 16.47, 13.68, 18.96]]}},
               "thesis_spindler", "cache",
               {f"{e}/{w}x{n}": [*eo, f"cache.network.n_neurons={w}", f"cache.network.n_hidden_layers={n}"]
                for e, eo in ENCODINGS.items() for w in (64, 128) for n in (3, 4, 5, 6)}, v_encodings_time,
               "inference 2^16 points (S: 2^21) + 4 training batches of 2^14 (as S), the cache alone", runs=1,
               params={"repeats": 3, "n_infer": 1 << 16, "batch": 1 << 14, "steps": 4}, plot=True),
    Experiment("S-5.2-Fig5.6", 11, "Training-only time against batch size", "S:691-698 (Fig 5.6)",
               "How does the training time grow with the batch size and the number of batches (T12/OB4, 6x64)?",
               {"claims": ["near-linear in the batch count; 2^16 samples cost 1.94 ms as one batch, 4.11 ms as 4 of "
                           "2^14 (derived)"],
                "table": {"columns": ["log2 batch", "1", "2", "3", "4", "5", "6"],
                          "rows": [[14, 1.25, 2.43, 3.37, 4.11, 5.15, 6.14], [15, 1.32, 2.51, 3.55, 4.63, 6.6, 7.12],
                                   [16, 1.94, 3.05, 4.75, 6.64, 8.06, 9.54],
                                   [17, 2.52, 4.68, 6.81, 9.36, 11.41, 13.85]]}},
               "thesis_spindler", "cache",
               {f"{k}x2^{s}": ENCODINGS["T12"] for s in (14, 15, 16, 17) for k in range(1, 7)},
               v_batch_time, "none (batch sizes 2^14..2^17 as S), the cache alone", runs=1,
               params={"repeats": 3}, plot=True),
    Experiment("S-5.3.1", 12, "Learning rate, EMA and flicker", "S:543-547, S:710",
               "Does an EMA of the weights (alpha 0.99) damp the flicker of a cache trained at lr 0.01?",
               {"claims": ["lr 0.01 flickers strongly; the EMA with alpha 0.99 damps it (visual, S:710)"]},
               "thesis_spindler", "curve", {"ema 0.99": [], "no EMA": ["cache.ema.alpha=0.0"]}, v_flicker,
               SCALE + "; 20 frames, 5 runs", runs=5, frames=20, explain=LADDER_OURS),
    Experiment("S-5.3.2", 13, "Encoding quality", "S:718-726 (Fig 5.7)",
               "Shortly after the start: colour shift, bias and relative variance of T12, F12 and the hash grid?",
               {"claims": ["T and F show a colour shift lasting seconds, worse for T; the hash grid's vanishes quickly",
                           "at 6x64 and 3x64, T and F have more bias than the hash grid; relative variance similar"]},
               "thesis_spindler", "curve",
               {f"{e}/{n}x64": [*ENCODINGS[e], f"cache.network.n_hidden_layers={n}"]
                for n in (6, 3) for e in ("T12", "F12", "MRHE12")}, v_encodings_quality,
               SCALE + "; 15 frames (S: seconds at ~30 FPS), 5 runs", runs=5, frames=15, plot=True,
               explain=[(n, o) for n, o in LADDER_OURS if not any(x.startswith("encoding") for x in o)]),
    # the encodings are the variants: the ladder's steps without the encoding's
    Experiment("S-5.3.3-Ex1", 14, "NRC against the path tracer: scene 0, density 0.6", "S:728-737 (Fig 5.8)",
               "At 1 spp, is NRC (6x64, MRHE12/OB4) less noisy than the path tracer, and how biased?",
               {"claims": ["NRC is much less noisy and underestimates dark regions (S:737)"],
                "table": {"columns": ["side", "MSE", "rBias", "rVar"],
                          "rows": [["PT", 0.403, "in [-0.01, 0.01]", 3.09], ["NRC", 0.311, -0.076, 2.38]]}},
               "thesis_spindler", "nrc_vs_pt", {"scene 0, density 0.6": []}, v_nrc_vs_pt("less_noise"),
               SCALE + "; NRC's 30th frame (frames before the capture not stated in S), 5 seeds", runs=5, frames=30,
               explain=LADDER_OURS),
    Experiment("S-5.3.3-Ex2", 15, "NRC against the path tracer: scene 0, density 0.25", "S:742-750 (Fig 5.9)",
               "As Ex1 in a thinner medium: does NRC's advantage shrink?",
               {"claims": ["NRC and the path tracer are about equal (S:750)"],
                "table": {"columns": ["side", "MSE", "rBias", "rVar"],
                          "rows": [["PT", 0.067, "in [-0.01, 0.01]", 1.02], ["NRC", 0.071, -0.048, 1.078]]}},
               "thesis_spindler", "nrc_vs_pt", {"scene 0, density 0.25": S0_025}, v_nrc_vs_pt("equal"),
               SCALE + "; NRC's 30th frame, 5 seeds", runs=5, frames=30, explain=LADDER_OURS),
    Experiment("S-5.3.3-Ex3", 16, "NRC against the path tracer: scene 1 (point light)", "S:755-757 (Fig 5.10)",
               "As Ex1 with a point light at the medium's centre.",
               {"claims": ["like Ex1: less noise, a slight negative bias, a 'nearly equal' error (S:757); the "
                           "printed NRC triple equals Ex2's (probably a copy error)"],
                "table": {"columns": ["side", "MSE", "rBias", "rVar"],
                          "rows": [["PT", 0.117, "in [-0.01, 0.01]", 5.38], ["NRC", 0.071, -0.048, 1.078]]}},
               "thesis_spindler", "nrc_vs_pt", {"scene 1, density 0.6": S1}, v_nrc_vs_pt("less_noise"),
               SCALE + "; NRC's 30th frame, 5 seeds", runs=5, frames=30, explain=LADDER_OURS),
    Experiment("S-4.2", 17, "Ring buffer (and infer filter)", "S:567, S:579, S:677-679, S:767",
               "Does the ring buffer of valid training records make the cache learn faster?",
               {"claims": ["depending on the camera the cache visibly learns faster with the ring buffer (S:767)",
                           "the infer filter's check costs nothing measurable; at 2^21 a batch covers the frame, so "
                           "it skips nothing (THESES.md)"]},
               "thesis_spindler", "curve",
               {"ring buffer": VIEWS["c"], "no ring buffer": [*VIEWS["c"], "renderer.training.ring_buffer=1"]},
               v_ring_buffer, SCALE + "; view c of F-6.2 (much empty screen: many invalid training paths); "
               "20 frames, 5 runs; 'no ring buffer' keeps 1 record (our minimum)", runs=5, frames=20, plot=True,
               explain=LADDER_OURS),
]
BY_ID = {e.id: e for e in EXPERIMENTS}


# ---------------------------------------------------------------------------- measurements
@dataclasses.dataclass
class Scale:
    width: int = 64
    height: int = 36
    train: int = 32  # the training image's side (square, a multiple of 16: the filters split it evenly)
    runs: int | None = None  # None: each experiment's own
    quick: bool = False
    ref_spp: int = 1024  # S: the reference is the path tracer at 1024 spp (S:730)
    quiet: bool = False
    explain: bool = True  # measure a disagreement's ladder
    explain_runs: int = 3  # runs of each ladder step (fewer than the experiment's: a ladder is 5 more measurements)

    def runs_of(self, exp: Experiment, ladder: bool = False) -> int:
        runs = 2 if self.quick else (self.runs or exp.runs)
        return min(runs, self.explain_runs) if ladder else runs

    def frames_of(self, exp: Experiment) -> int:
        return min(exp.frames, 8 if exp.kind == "curve" else 3) if self.quick else exp.frames

    def overrides(self, exp: Experiment, variant: list[str]) -> list[str]:
        return [f"+experiment={exp.config}", f"scene.camera.width={self.width}", f"scene.camera.height={self.height}",
                f"renderer.training.width={self.train}", f"renderer.training.height={self.train}", *variant]


def reference_for(nrc_cfg: Any, scale: Scale) -> Any:
    """The converged reference of an NRC config's scene (the path tracer, ratio tracking), rendered when missing."""
    from omegaconf import OmegaConf

    from nrc.config import compose
    from nrc.evaluation.reference import default_reference_path, read_reference
    from nrc.reference_app import ensure_reference

    scene = OmegaConf.to_container(nrc_cfg.scene, resolve=True)
    pt = [*scene_overrides(scene), "renderer=pt", "transmittance=ratio"]
    spp = 16 if scale.quick else scale.ref_spp
    path = default_reference_path(compose(pt), spp)
    if not path.is_file():
        print(f"theses: rendering the reference {repo_relative(path)} ({spp} spp)", flush=True)
    ref = read_reference(ensure_reference(pt, spp, max(1, min(64, spp // 4))))
    return ref, path, pt


def variant_setup(exp: Experiment, scale: Scale, variant: list[str], extra: Sequence[str]) -> tuple:
    """A variant's loaded setup, its reference (rendered when missing), the reference's path, the path tracer's
    overrides, the reference image (float64) and its medium mask."""
    from lab.render import setup
    from nrc.metrics import medium_mask

    s = setup(scale.overrides(exp, [*variant, *extra]))
    ref, ref_path, pt_ovs = reference_for(s.cfg, scale)
    return s, ref, ref_path, pt_ovs, ref.image.astype(np.float64), medium_mask(ref.alpha)


def measure_curve(exp: Experiment, scale: Scale, extra: Sequence[str] = ()) -> dict:
    from tqdm import tqdm

    from lab.render import nrc_run, run_seeds
    from nrc.metrics import error_report, mean_ratio, rel_mse

    runs, frames = scale.runs_of(exp), scale.frames_of(exp)
    out: dict[str, Any] = {"variants": {}, "frames": frames, "runs": runs}
    for name, variant in exp.variants.items():
        s, ref, ref_path, _, image, mask = variant_setup(exp, scale, variant, extra)
        floor, scale_ref = ref.rel_mse_floor_medium or 0.0, float(image[mask].mean()) if mask.any() else 1.0
        per_run: list[list[dict]] = []
        last: list[np.ndarray] = []
        with tqdm(total=runs * frames, desc=f"{exp.id} {name}", unit="frame", disable=scale.quiet) as bar:
            for seed in run_seeds(runs):
                rows: list[dict] = []
                prev: list[np.ndarray | None] = [None]

                def on_frame(frame, img, output, stats, rows=rows, prev=prev):
                    x = np.nan_to_num(np.asarray(img, np.float64))
                    any_px = bool(mask.any())
                    rows.append({
                        "loss": float(stats["loss"]) if stats.get("loss") is not None else None,
                        "rel_mse": rel_mse(x, image, mask) - floor if any_px else None,
                        "mean_ratio": mean_ratio(x, image, mask) if any_px else None,
                        "chroma": chroma(x, image, mask) if any_px else None,
                        "flicker": (float(np.abs(x - prev[0])[mask].mean()) / scale_ref
                                    if prev[0] is not None and any_px else None)})
                    prev[0] = x
                    if frame == frames - 1:
                        last.append(x)
                    bar.update(1)

                nrc_run(s.scene, s.cfg, 1, seed, frames, False, on_frame)
                per_run.append(rows)
        keys = ("loss", "rel_mse", "mean_ratio", "chroma", "flicker")
        table = []
        for f in range(frames):
            row: dict[str, Any] = {"frame": f + 1}
            for k in keys:
                row[k], row[k + "_ci"] = ci95([r[f][k] for r in per_run])
            table.append(row)
        final = error_report(np.stack(last), image, mask)["medium"] if len(last) >= 2 and mask.any() else None
        out["variants"][name] = {"rows": table, "final": final, "overrides": variant,
                                 "reference": repo_relative(ref_path), "reference_floor": floor}
    return out


def measure_nrc_vs_pt(exp: Experiment, scale: Scale, extra: Sequence[str] = ()) -> dict:
    from tqdm import tqdm

    from lab.render import SEED_BASE, nrc_run, pt_render, pt_warmup, run_seeds, setup
    from nrc.metrics import error_report

    runs, frames = scale.runs_of(exp), scale.frames_of(exp)
    out: dict[str, Any] = {"variants": {}, "frames": frames, "runs": runs}
    for name, variant in exp.variants.items():
        s, ref, ref_path, pt_ovs, image, mask = variant_setup(exp, scale, variant, extra)
        nrc_imgs, trace = [], []
        for seed in tqdm(run_seeds(runs), desc=f"{exp.id} {name} NRC", unit="run", disable=scale.quiet):
            def on_frame(frame, img, output, stats):
                if frame >= 1:
                    trace.append(float(stats["time_trace_s"]))
                if frame == frames - 1:
                    nrc_imgs.append(np.nan_to_num(np.asarray(img, np.float64)))

            nrc_run(s.scene, s.cfg, 1, seed, frames, False, on_frame)
        res: dict[str, Any] = {"nrc": sides_metrics(np.stack(nrc_imgs), image, mask, error_report),
                               "overrides": variant, "reference": repo_relative(ref_path)}
        res["nrc"]["trace_s"] = float(np.mean(trace)) if trace else None
        if exp.params.get("pt", True):
            p = setup([*pt_ovs, f"renderer.backend={s.cfg.renderer.backend}"])
            pt_warmup(p.scene, p.cfg)
            imgs, times = [], []
            for seed in run_seeds(runs, SEED_BASE + 500):
                img, dt = pt_render(p.scene, p.cfg, 1, seed)
                imgs.append(img.astype(np.float64))
                times.append(dt)
            res["pt"] = sides_metrics(np.stack(imgs), image, mask, error_report)
            res["pt"]["trace_s"] = float(np.mean(times))
        out["variants"][name] = res
    return out


def sides_metrics(xs: np.ndarray, ref: np.ndarray, mask: np.ndarray, error_report: Callable) -> dict:
    """The errors of renders ``xs`` over the medium: ``error_report``'s and the thesis's signed relative bias."""
    rep = dict(error_report(xs, ref, mask)["medium"])
    rep["thesis_signed_bias"] = float(np.mean([x[mask].mean() / ref[mask].mean() - 1 for x in xs]))
    return rep


def measure_timing(exp: Experiment, scale: Scale, extra: Sequence[str] = ()) -> dict:
    from tqdm import tqdm

    from lab.render import SEED_BASE, nrc_run, nrc_warmup, setup
    from nrc.metrics import medium_mask
    from nrc.render.preview import medium_alpha

    warm, frames = exp.params.get("warm", 1), scale.frames_of(exp)
    out: dict[str, Any] = {"variants": {}, "frames": frames, "warm": warm, "runs": 1}
    warmed = False
    for name, variant in tqdm(exp.variants.items(), desc=exp.id, unit="variant", disable=scale.quiet):
        s = setup(scale.overrides(exp, [*variant, *extra]))
        if not warmed:
            nrc_warmup(s.scene, s.cfg.copy())
            warmed = True
        stats_kept: list[dict] = []

        def on_frame(frame, img, output, stats):
            if frame >= warm:
                stats_kept.append({k: float(stats.get(k) or 0.0) for k in
                                   ("time_trace_s", "time_infer_s", "time_train_s", "time_train_work_s",
                                    "time_frame_s", "train_steps")})

        nrc_run(s.scene, s.cfg, 1, SEED_BASE, warm + frames, False, on_frame)
        row: dict[str, Any] = {"overrides": variant,
                               "medium_fraction": float(medium_mask(medium_alpha(s.scene)).mean())}
        for k in stats_kept[0]:
            row[k], row[k + "_ci"] = ci95([x[k] for x in stats_kept])
        # the training pass besides its steps: the records, the batch filter (S's Prepare-Train-Rays)
        row["time_other_s"] = max(0.0, row["time_train_s"] - row["time_train_work_s"])
        out["variants"][name] = row
    return out


def measure_cache(exp: Experiment, scale: Scale, extra: Sequence[str] = ()) -> dict:
    """Inference and training steps of the cache alone, on random points in the medium's box."""
    import torch
    from tqdm import tqdm

    from lab.render import setup
    from nrc.cache import build_radiance_cache

    reps = 1 if scale.quick else exp.params.get("repeats", 3)
    shrink = 6 if scale.quick else 0  # quick: batch sizes / 64
    out: dict[str, Any] = {"variants": {}, "repeats": reps, "runs": 1, "shrink_log2": shrink}
    grid = None
    gen = torch.Generator().manual_seed(0)
    for name, variant in tqdm(exp.variants.items(), desc=exp.id, unit="config", disable=scale.quiet):
        s = setup(scale.overrides(exp, [*variant, *extra])) if grid is None else None
        cfg = s.cfg if s is not None else _compose(scale.overrides(exp, [*variant, *extra]))
        if s is not None:
            grid = s.scene.grid
        cache = build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, grid, "cpu", 0,
                                     training_paths=scale.train * scale.train)
        if exp.params.get("split") or "x2^" in name:  # "<k>x2^<s>": k steps of 2^s
            k, s_log2 = name.split("x2^")
            steps, batch, n_infer = int(k), 1 << max(4, int(s_log2) - shrink), 0
        else:
            steps, batch, n_infer = exp.params["steps"], exp.params["batch"] >> shrink, exp.params["n_infer"] >> shrink
        lo, hi = grid.box.lo, grid.box.hi

        def points(n: int) -> tuple[Any, Any, Any]:
            x = torch.as_tensor(lo) + torch.rand(n, 3, generator=gen) * (torch.as_tensor(hi) - torch.as_tensor(lo))
            d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=1)
            return x.float(), d.float(), torch.rand(n, 3, generator=gen)

        data = [points(batch) for _ in range(steps)]
        qx, qd, _ = points(max(n_infer, 1))
        cache.train_step(*data[0])  # first-use costs
        infer, train = [], []
        for _ in range(reps):
            t0 = time.perf_counter()
            if n_infer:
                cache.query(qx, qd)
            t1 = time.perf_counter()
            for b in data:
                cache.train_step(*b)
            t2 = time.perf_counter()
            infer.append(t1 - t0)
            train.append(t2 - t1)
        out["variants"][name] = {"overrides": variant, "steps": steps, "batch": batch, "n_infer": n_infer,
                                 "infer_s": float(np.median(infer)), "train_s": float(np.median(train)),
                                 "total_s": float(np.median(infer) + np.median(train))}
    return out


def _compose(overrides: list[str]) -> Any:
    from nrc.config import compose

    return compose(overrides)


MEASURE: dict[str, Callable[..., dict]] = {"curve": measure_curve, "nrc_vs_pt": measure_nrc_vs_pt,
                                          "timing": measure_timing, "cache": measure_cache}


def run_experiment(exp: Experiment, scale: Scale, saved: dict | None = None) -> dict:
    """Measure ``exp`` (or read the experiment it reuses, or ``saved``: an earlier result of it, whose measurement
    is kept), its verdict, and for a disagreement its ladder."""
    import torch

    t0 = time.perf_counter()
    if saved is not None:
        data, settings = saved["data"], {**saved["settings"], "explain": True,
                                         "ladder_runs": scale.runs_of(exp, ladder=True)}
    elif exp.reuse:
        src = OUT / f"{exp.reuse}.json"
        if not src.is_file():
            raise SystemExit(f"theses: {exp.id} reads {exp.reuse}'s runs: run --only {exp.reuse} first")
        base = json.loads(src.read_text())
        data, settings = base["data"], base["settings"]
    else:
        data = MEASURE[exp.kind](exp, scale)
        settings = {"width": scale.width, "height": scale.height, "training": [scale.train, scale.train],
                    "quick": scale.quick, "ref_spp": 16 if scale.quick else scale.ref_spp,
                    "ladder_runs": scale.runs_of(exp, ladder=True), "explain": scale.explain}
    verdict, reason = exp.verdict(data)
    ladder = []
    if verdict == "disagrees" and exp.explain and not exp.reuse and scale.explain:
        extra: list[str] = []
        small = dataclasses.replace(scale, runs=scale.runs_of(exp, ladder=True))
        for step, ovs in exp.ladder()[:2] if scale.quick else exp.ladder():  # quick: the ladder's first steps
            extra = [*extra, *ovs]
            v, r = exp.verdict(MEASURE[exp.kind](exp, small, extra))
            ladder.append({"step": step, "overrides": list(ovs), "verdict": v, "reason": r})
    return {"id": exp.id, "data": data, "verdict": verdict, "reason": reason, "ladder": ladder,
            "settings": settings, "seconds": time.perf_counter() - t0, "machine": machine(),
            "threads": torch.get_num_threads(),
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "command": f"python scripts/theses.py --only {exp.id}{' --quick' if scale.quick else ''} --force"}


# ---------------------------------------------------------------------------- pages
def thesis_table(exp: Experiment) -> list[str]:
    t = exp.thesis.get("table")
    if not t:
        return []
    return [f"| {' | '.join(t['columns'])} |", "|" + "---|" * len(t["columns"]),
            *[f"| {' | '.join(str(c) for c in row)} |" for row in t["rows"]], ""]  # the thesis's digits, as printed


def ours_table(exp: Experiment, data: dict) -> list[str]:
    """Our numbers, in the shape of the measurement kind."""
    v = data["variants"]
    if exp.kind == "curve":
        frames = sorted({1, 2, 4, 8, 16, 25, 32, 64, data["frames"]} & set(range(1, data["frames"] + 1)))
        lines = ["Means over the runs ± 95 % interval (relMSE over the medium, the reference's noise floor "
                 "subtracted; mean: the image mean over the reference's; colour: max/min per-channel mean ratio - 1; "
                 "flicker: mean |I_t - I_t-1| over the reference's mean).", "",
                 "| variant | frame | loss | relMSE | mean / ref | colour | flicker |",
                 "|---|---:|---:|---:|---:|---:|---:|"]
        for name, res in v.items():
            for r in res["rows"]:
                if r["frame"] in frames:
                    cells = [pm(r[k], r[k + "_ci"]) for k in ("loss", "rel_mse", "mean_ratio", "chroma", "flicker")]
                    lines.append(f"| {name} | {r['frame']} | {' | '.join(cells)} |")
        lines += ["", "At the last frame, the runs as independent renders (over the medium):", "",
                  "| variant | MSE | signed rel. bias | rel. variance | thesis rBias | thesis rVar |",
                  "|---|---:|---:|---:|---:|---:|"]
        for name, res in v.items():
            f = res.get("final") or {}
            lines.append(f"| {name} | {fmt(f.get('mse'))} | {fmt(f.get('signed_relative_bias'))} | "
                         f"{fmt(f.get('relative_variance'))} | {fmt(f.get('thesis_relative_bias'))} | "
                         f"{fmt(f.get('thesis_relative_variance'))} |")
        return lines
    if exp.kind == "nrc_vs_pt":
        lines = ["| variant | side | MSE | rBias (thesis: mean(x)/mean(r) - 1) | rVar (thesis: var(x)/mean(r)) | "
                 "signed rel. bias (per pixel) | rel. variance (per pixel) | relMSE | trace s |",
                 "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
        for name, res in v.items():
            for side in ("pt", "nrc"):
                m = res.get(side)
                if m:
                    lines.append(f"| {name} | {side.upper()} | {fmt(m['mse'])} | {fmt(m['thesis_signed_bias'])} | "
                                 f"{fmt(m['thesis_relative_variance'])} | {fmt(m['signed_relative_bias'])} | "
                                 f"{fmt(m['relative_variance'])} | {fmt(m['rel_mse'])} | {fmt(m['trace_s'])} |")
        return lines
    if exp.kind == "timing":
        lines = ["Means over the frames (ms), ± 95 % interval; batches: training steps a frame.", "",
                 "| variant | trace | inference | training | of it, not steps | frame | batches | medium on screen |",
                 "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for name, r in v.items():
            ms = [pm(r[k] * 1e3, (r[k + "_ci"] or 0) * 1e3 or None)
                  for k in ("time_trace_s", "time_infer_s", "time_train_s")]
            lines.append(f"| {name} | {' | '.join(ms)} | {fmt(r['time_other_s'] * 1e3)} | "
                         f"{fmt(r['time_frame_s'] * 1e3)} | {fmt(r['train_steps'])} | {r['medium_fraction']:.0%} |")
        return lines
    lines = [f"Medians over {data['repeats']} repeats (ms).", "",
             "| config | training steps | batch | inference points | inference | training | total |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for name, r in v.items():
        lines.append(f"| {name} | {r['steps']} | {r['batch']} | {r['n_infer']} | {fmt(r['infer_s'] * 1e3)} | "
                     f"{fmt(r['train_s'] * 1e3)} | {fmt(r['total_s'] * 1e3)} |")
    return lines


def settings_table(exp: Experiment) -> list[str]:
    """The thesis's settings and ours side by side: the keys the thesis config sets, against our defaults."""
    from omegaconf import OmegaConf

    keys = ["cache.network.n_neurons", "cache.network.n_hidden_layers", "cache.optimizer.lr", "encoding.position.otype",
            "encoding.position.n_levels", "encoding.position.lr", "encoding.position.log2_hashmap_size",
            "encoding.position.lazy", "encoding.direction.n_bins", "cache.ema.alpha", "cache.ema.window_fraction",
            "cache.ema.hold_window_fraction",
            "extra_inputs.density", "batch_filter.name",
            "renderer.termination.min_vertices", "renderer.termination.p_continue", "renderer.cache_target",
            "renderer.training.unbiased_fraction", "renderer.training.carry_frames", "renderer.training.ring_buffer",
            "scene.volume.density_scale", "scene.volume.albedo", "scene.volume.g", "scene.integrator.max_scatter",
            "transmittance.name"]
    thesis = _compose([f"+experiment={exp.config}"])
    ours = _compose(["renderer=nrc"])
    lines = [f"| key | {exp.config} (`conf/experiment/{exp.config}.yaml`) | our defaults |", "|---|---|---|"]
    for k in keys:
        a, b = OmegaConf.select(thesis, k, default=None), OmegaConf.select(ours, k, default=None)
        lines.append(f"| `{k}` | {fmt(a)} | {fmt(b)}{'' if a == b else ' ≠'} |")
    return lines


def page(exp: Experiment, res: dict) -> str:
    s = res["settings"]
    lines = [f"# {exp.id}: {exp.title}", "", f"Source: {exp.source} (map: `../shared/THESES.md`, #{exp.number}). "
             "Generated by `scripts/theses.py`; do not edit.", "", f"**Question.** {exp.question}", "",
             f"**Verdict: {res['verdict']}.** {res['reason']}", "", "## The thesis", "",
             *[f"- {c}" for c in exp.thesis.get("claims", [])], "", *thesis_table(exp), "## Settings", "",
             f"Run at `conf/experiment/{exp.config}.yaml` plus each variant's overrides; measured as `{exp.kind}`, "
             f"{res['data'].get('runs', 1)} run(s) of {res['data'].get('frames', '–')} frame(s), "
             f"{s['width']}x{s['height']}, training image {s['training'][0]}x{s['training'][1]}"
             f"{' (--quick: a smoke test, not a result)' if s.get('quick') else ''}.", "",
             f"Scaled for the CPU: {exp.scaled}.", "", "Variants:", "",
             *[f"- {n}: `{' '.join(o) or '(the config as it is)'}`" for n, o in exp.variants.items()], "",
             *settings_table(exp), "", "## Ours", "", *ours_table(exp, res["data"]), ""]
    if exp.plot:
        lines += [f"![{exp.id}]({exp.id}.png)", ""]
    if res["verdict"] == "disagrees" and exp.explain and not res["ladder"]:
        lines += ["## What changes the answer", "", "Not measured in this run (`--no-explain`): "
                  f"`python scripts/theses.py --only {exp.id} --force` measures the ladder "
                  f"({', '.join(n for n, _ in exp.explain)}).", ""]
    if res["ladder"]:
        lines += ["## What changes the answer", "", f"The same measurement ({s.get('ladder_runs', '–')} runs a step) at "
                  "each step from the thesis's settings towards ours (cumulative):", "",
                  "| step | overrides added | verdict | numbers |", "|---|---|---|---|",
                  "| the thesis's settings | – | " + f"{res['verdict']} | {res['reason']} |"]
        lines += [f"| {r['step']} | `{' '.join(r['overrides'])}` | {r['verdict']} | {r['reason']} |"
                  for r in res["ladder"]]
        changed = next((r["step"] for r in res["ladder"] if r["verdict"] != res["verdict"]), None)
        lines += ["", f"The step that changes the answer: {changed or 'none of them'}.", ""]
    lines += ["## Reproduce", "", f"`{res['command']}` ({res['seconds']:.0f} s), then `python scripts/theses.py "
              "--report`.", "", f"Machine: {res['machine']}; {res['date']}.", ""]
    if res.get("ladder_run"):
        lr = res["ladder_run"]
        lines += [f"The ladder re-measured after a change of our defaults (the measurement above kept): "
                  f"`{lr['command']}` ({lr['seconds']:.0f} s); machine: {lr['machine']}; {lr['date']}.", ""]
    return "\n".join(lines)


def plot(exp: Experiment, res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = res["data"]
    if exp.kind == "curve":
        keys = ("loss", "rel_mse", "mean_ratio", "chroma")
        fig, axes = plt.subplots(1, 4, figsize=(15, 3.6))
        for ax, key in zip(axes, keys):
            for name in d["variants"]:
                f, m = series(d, name, key)
                h = [r.get(key + "_ci") or 0.0 for r in d["variants"][name]["rows"]]
                m = np.array([np.nan if x is None else x for x in m], dtype=float)
                ax.plot(f, m, label=name, lw=1.2)
                lo = m - np.array(h)
                if key in ("loss", "rel_mse"):  # log axes: a band's lower edge at or below 0 kept in view
                    lo = np.maximum(lo, 0.1 * np.abs(m))
                ax.fill_between(f, lo, m + np.array(h), alpha=0.2, lw=0)
            ax.set_title(key)
            ax.set_xlabel("frame")
            if key in ("loss", "rel_mse"):
                ax.set_yscale("log")
            ax.grid(True, lw=0.3)
        axes[0].legend(fontsize=7)
    else:
        fig, ax = plt.subplots(figsize=(10, 3.8))
        names = list(d["variants"])
        key = {"timing": "time_trace_s", "cache": "total_s"}.get(exp.kind)
        if key:
            ax.bar(range(len(names)), [d["variants"][n][key] * 1e3 for n in names])
            ax.set_ylabel(f"{key} (ms)")
        else:
            ax.bar(range(len(names)), [d["variants"][n]["nrc"]["mse"] for n in names])
            ax.set_ylabel("NRC MSE")
        ax.set_xticks(range(len(names)), names, rotation=90, fontsize=6)
    fig.suptitle(f"{exp.id}: {exp.title} ({res['settings']['width']}x{res['settings']['height']})")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write(exp: Experiment, res: dict, out: Path | None = None) -> Path:
    out = out or OUT
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{exp.id}.json").write_text(json.dumps(res, indent=1, default=float))
    if exp.plot:
        plot(exp, res, out / f"{exp.id}.png")
    (out / f"{exp.id}.md").write_text(page(exp, res))
    return out / f"{exp.id}.md"


def index(results: dict[str, dict]) -> str:
    lines = ["# The theses' experiments, re-run", "", "One page per experiment of Fedotov 2024 (F) and Spindler 2022 "
             "(S) (map: `../shared/THESES.md`, section 2), at the theses' own settings "
             "(`conf/experiment/thesis_spindler.yaml`, `conf/experiment/thesis_fedotov.yaml`), scaled for a CPU as "
             "each page says. Generated by `python scripts/theses.py` (`--report`: from the jsons).", "",
             "| # | id | title | verdict | numbers |", "|---:|---|---|---|---|"]
    for exp in EXPERIMENTS:
        r = results.get(exp.id)
        verdict = f"**{r['verdict']}**{' (quick)' if r['settings'].get('quick') else ''}" if r else "not run"
        lines.append(f"| {exp.number} | [{exp.id}]({exp.id}.md) | {exp.title} | {verdict} | "
                     f"{(r or {}).get('reason', '–').replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def report(out: Path | None = None) -> Path:
    """Every page and the index again from the jsons in ``out`` (default :data:`OUT`)."""
    out = out or OUT
    results = {}
    for exp in EXPERIMENTS:
        f = out / f"{exp.id}.json"
        if f.is_file():
            results[exp.id] = json.loads(f.read_text())
            write(exp, results[exp.id], out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "README.md").write_text(index(results))
    return out / "README.md"


def fresh(path: Path, scale: Scale) -> bool:
    """Whether the result at ``path`` exists and was measured at ``scale`` (a --quick smoke test's result never
    stands in for a measurement, nor one of another frame size)."""
    if not path.is_file():
        return False
    s = json.loads(path.read_text()).get("settings", {})
    return (s.get("quick"), s.get("width"), s.get("height")) == (scale.quick, scale.width, scale.height)


# ---------------------------------------------------------------------------- command line
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--only", default=None, help=f"comma-separated ids (default: all): {', '.join(BY_ID)}")
    p.add_argument("--quick", action="store_true", help="a smoke test: 32x18, 2 runs, a few frames, 16-spp references")
    p.add_argument("--runs", type=int, default=None, help="runs (seeds) of every experiment (default: each its own)")
    p.add_argument("--width", type=int, default=None, help="frame width (default 64; --quick 32)")
    p.add_argument("--height", type=int, default=None, help="frame height (default 36; --quick 18)")
    p.add_argument("--train", type=int, default=32, help="the training image's side, a multiple of 16 (default 32)")
    p.add_argument("--threads", type=int, default=None, help="torch's CPU threads (default: torch's; 1 on a busy "
                   "machine: 2 threads on 2 busy cores made a training step 35x slower)")
    p.add_argument("--ref-spp", type=int, default=1024, help="the references' spp (S: 1024)")
    p.add_argument("--no-explain", action="store_true", help="no ladder for a disagreement (it costs ~3x the run)")
    p.add_argument("--explain-only", action="store_true",
                   help="the ladders of the saved results' disagreements, their measurements kept (no re-run); "
                   "with --force also the ladders already measured (after a change of our defaults)")
    p.add_argument("--force", action="store_true", help="re-run experiments whose json exists")
    p.add_argument("--report", action="store_true", help="only regenerate the pages from the jsons")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--jobs", choices=["none", "local", "slurm"], default="none",
                   help="each missing experiment as its own job (submitit)")
    p.add_argument("--slurm", action="append", default=[], metavar="KEY=VALUE")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser().parse_args(argv)
    ids = list(BY_ID) if not args.only else [i.strip() for i in args.only.split(",") if i.strip()]
    unknown = [i for i in ids if i not in BY_ID]
    if unknown:
        raise SystemExit(f"theses: unknown experiment {', '.join(unknown)} (known: {', '.join(BY_ID)})")
    if (args.runs is not None and args.runs < 2) or (args.width or 16) < 16 or (args.height or 9) < 9 \
            or args.train < 16 or args.train % 16:
        raise SystemExit("theses: --runs must be >= 2 (95 % intervals), --width >= 16, --height >= 9, --train a "
                         "multiple of 16")
    os.chdir(REPO)  # the configs' VDB path and the references are relative to the repo root
    if args.report:
        print(f"wrote {repo_relative(report())}")
        return 0
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    scale = Scale(width=args.width or (32 if args.quick else 64), height=args.height or (18 if args.quick else 36),
                  train=16 if args.quick else args.train, runs=args.runs, quick=args.quick, ref_spp=args.ref_spp,
                  quiet=args.quiet, explain=not args.no_explain)
    if args.explain_only:
        for i in ids:
            path = OUT / f"{i}.json"
            saved = json.loads(path.read_text()) if path.is_file() else None
            if saved is None or not fresh(path, scale) or saved["verdict"] != "disagrees" \
                    or (saved.get("ladder") and not args.force) or not BY_ID[i].explain or BY_ID[i].reuse:
                continue
            res = run_experiment(BY_ID[i], dataclasses.replace(scale, explain=True), saved)
            # the measurement's own seconds, machine and date are kept; the ladder's run is recorded beside them
            res["ladder_run"] = {k: res[k] for k in ("seconds", "machine", "threads", "date")}
            res["ladder_run"]["command"] = f"python scripts/theses.py --only {i} --explain-only --force"
            res.update({k: saved[k] for k in ("seconds", "machine", "threads", "date", "command") if k in saved})
            print(f"[{i}] ladder: {[(s['step'], s['verdict']) for s in res['ladder']]} -> {repo_relative(write(BY_ID[i], res))}",
                  flush=True)
        print(f"wrote {repo_relative(report())}")
        return 0
    todo = [i for i in ids if args.force or not fresh(OUT / f"{i}.json", scale)]
    for i in ids:
        if i not in todo:
            print(f"[{i}] kept {repo_relative(OUT / f'{i}.json')} (--force to re-run)")
    if args.jobs != "none" and todo:
        script = [sys.executable, str(REPO / "scripts" / "theses.py"), *without_jobs(argv)]
        run_commands({i: [*script, "--only", i] for i in todo}, args.jobs, OUT / ".jobs", REPO, args.slurm)
    else:
        for i in sorted(todo, key=lambda i: BY_ID[i].reuse is not None):  # a reused measurement first
            res = run_experiment(BY_ID[i], scale)
            print(f"[{i}] {res['verdict']}: {res['reason']} ({res['seconds']:.0f} s) -> {repo_relative(write(BY_ID[i], res))}",
                  flush=True)
    print(f"wrote {repo_relative(report())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
