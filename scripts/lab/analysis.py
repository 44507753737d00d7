"""Equal-time comparisons of renderers: the path tracer's Pareto front (the best error reachable within a time),
log-log interpolation, equal-time ratios (single frames, or accumulated running means) and crossovers, raw and
against denoised twins (``+oidn``). Rows are dicts with ``mode``, ``config``, ``renderer``, ``spp``, ``time_s`` and
the errors (``rel_mse``, ``rel_mse_medium``, ...), as ``scripts/speed_vs_error.py`` writes them; the mean over
independent runs with its 95 % interval (:func:`ci95`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


DENOISED = "+oidn"  # suffix of a configuration's denoised twin


def ci95(values: Any) -> tuple[float | None, float | None]:
    """Mean of the finite, non-None ``values`` and the half-width of its 95 % interval (t-quantile x standard
    error; None below 2 values; ``(None, None)`` without any)."""
    from scipy.stats import t

    x = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=np.float64)
    if len(x) == 0:
        return None, None
    if len(x) < 2:
        return float(x.mean()), None
    return float(x.mean()), float(t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x)))


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
