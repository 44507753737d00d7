"""``docs/results.md`` and the README's generated block, from the measurements under ``docs/results/``.

``python scripts/experiments_report.py --results`` assembles ``docs/results.md`` from ``docs/results_intro.md``
(hand-written, linked), the ``scripts/speed_vs_error.py`` outputs listed in :data:`SPEED_RUNS`
(``docs/results/<run>/``) and the crossover maps (``scripts/crossover_map.py``), links the theses' experiments
(``scripts/theses.py``: ``docs/theses/README.md``), and rewrites the README's one generated block, the lines
between ``<!-- generated: scripts/experiments_report.py --results: results -->`` and ``<!-- end generated -->``:
what NRC found in one sentence, the crossover map's table (cold and warm cache) and its figure
(:func:`readme_results`, from ``docs/results/crossover_160x90*/map.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

from lab import REPO
from lab.tables import fmt  # one number format for every generated table

# the front-lit runs' renderer (commits ed8b100-e0a394f): before the shared transport core (nrc/render/wavefront/)
# and the current NRC defaults (docs/nrc.md, "Current defaults and why")
EARLIER = "earlier version of the renderer, before the shared transport core"
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
              *[(f"unbiased training paths 1/4 against 1/2 (training.unbiased_fraction): {label}, 160 x 90",
                 f"unbiased_half_160x90_{name}") for label, name in (
                  ("the side-lit Disney cloud", "side_lit"), ("the default cumulus", "cumulus"),
                  ("the thin back-lit Disney cloud", "back_lit_thin"),
                  ("a point light below the Disney cloud", "point_below"))],
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
              ("front-lit preset (sun_front), raw path tracer, 480 x 270 (" + EARLIER + ", commit ed8b100)",
               "speed_480x270_v2"),
              ("front-lit preset (sun_front), raw path tracer, 160 x 90 (" + EARLIER + ", commit ed8b100)",
               "speed_160x90_v2"),
              ("front-lit preset, 160 x 90, the default sweep (encodings, extra inputs, transmittance estimators; "
               + EARLIER + ", commit ed8b100)", "speed_160x90_sweep_v2"),
              ("front-lit preset, 160 x 90, accumulated frames with a static camera (2 threads; " + EARLIER
               + ", commit e0a394f)", "speed_160x90_accumulate_crossover"),
              ("front-lit preset, 80 x 45, accumulated frames with a static camera (" + EARLIER
               + ", commits ed8b100 and e0a394f)", "speed_80x45_accumulate_crossover")]
HEADLINE = "nrc"  # the NRC configuration of the headline runs (its denoised twin is nrc+oidn)
HEADLINE_RUNS = ("oidn_480x270_side_lit", "oidn_160x90_side_lit")  # the first one present is the headline


def _ratio(summary: dict, config: str, baseline: str) -> dict | None:
    for q in summary.get("equal_time", []):
        if q["config"] == config and q.get("baseline", "pt") == baseline and q.get("ratio_rel_mse_medium"):
            return q
    return None


def _row(summary: dict, config: str) -> dict | None:
    return next((r for r in summary.get("rows", []) if r["config"] == config and r["mode"] == "single"), None)


def _warmup(summary: dict) -> str:
    """NRC's warm-up frames of a ``speed_vs_error`` run (its ``--warmup``), ``?`` when not recorded."""
    argv = (summary.get("meta") or {}).get("argv") or []
    return argv[argv.index("--warmup") + 1] if "--warmup" in argv[:-1] else "?"


def scene_type_ratios(summaries: dict[str, tuple[str, dict]]) -> list[dict[str, Any]]:
    """NRC + OIDN against the path tracer + OIDN at equal time per frame, one entry per run against the path
    tracer plus a denoiser (``oidn_*``) that has the ratio: the numbers of the headline and of the README's
    figure caption."""
    out = []
    for name, (label, summ) in summaries.items():
        den, row = _ratio(summ, HEADLINE + "+oidn", "pt+oidn"), _row(summ, HEADLINE + "+oidn")
        if not name.startswith("oidn_") or den is None or row is None:
            continue
        out.append({"name": name, "label": label, "ratio": den["ratio_rel_mse_medium"], "time_s": den["time_s"],
                    "mean": row.get("mean_ratio_medium"), "spp": row.get("spp"), "warmup": _warmup(summ)})
    return out


def scene_type_table(summaries: dict[str, tuple[str, dict]]) -> list[str]:
    """One row per run against the path tracer plus a denoiser (``oidn_*``): the equal-time relMSE ratios over
    the medium pixels raw and denoised, the image means, HDR-FLIP, and the earlier NRC defaults (``nrc_v1``)."""
    lines = ["| run | NRC / pt | NRC+OIDN / pt+OIDN | NRC / pt+OIDN | NRC+OIDN mean / ref | pt+OIDN mean / ref "
             "(nearest time) | HDR-FLIP NRC+OIDN / pt+OIDN | earlier defaults (`nrc_v1`): NRC+OIDN / pt+OIDN, mean |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, (label, summ) in summaries.items():
        den, row = _ratio(summ, HEADLINE + "+oidn", "pt+oidn"), _row(summ, HEADLINE + "+oidn")
        if not name.startswith("oidn_") or den is None or row is None:  # no single denoised NRC frame: accumulated
            continue
        raw, cross = _ratio(summ, HEADLINE, "pt"), _ratio(summ, HEADLINE, "pt+oidn")
        old, row_old = _ratio(summ, "nrc_v1+oidn", "pt+oidn"), _row(summ, "nrc_v1+oidn")
        pts = [r for r in summ["rows"] if r["mode"] == "single" and r.get("denoised") and r["renderer"] == "pt"]
        near = min(pts, key=lambda r: abs(r["time_s"] - den["time_s"])) if pts else {}
        lines.append(
            f"| {label}, {_warmup(summ)} warm-up frames | {fmt(raw and raw['ratio_rel_mse_medium'], 2)} | "
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
    others = [f"{q['label']}: {q['ratio']:.2g} (mean {fmt(q['mean'], 3)})" for q in scene_type_ratios(summaries)
              if q["name"] != name]
    if others:
        text += ". The same ratio on the other runs: " + "; ".join(others)
    return [text + ". A ratio above 1 means the path tracer plus a denoiser is better at equal time.", ""]


def _speed_section(docs: Path, label: str, name: str) -> tuple[list[str], dict | None]:
    """The run's own page (``docs/results/<name>/README.md``: the command, its time, the table and the plot) and
    its summary; ``([], None)`` when the run is missing."""
    d = docs / "results" / name
    if not (d / "summary.json").is_file():
        return [], None
    summary = json.loads((d / "summary.json").read_text())
    meta = summary["meta"]
    argv = " ".join(meta.get("argv") or [])
    lines = [f"# {label}", "", "Generated by `python scripts/experiments_report.py --results` (a run of "
             "[`docs/results.md`](../../results.md)).", "",
             f"Command (repo root): `python scripts/speed_vs_error.py {argv}` — took {meta['wall_time_s']:.0f} s. "
             f"Files: [`CSV`](speed_vs_error.csv), [`summary.json`](summary.json).", "",
             (d / "speed_vs_error.md").read_text(), "", f"![speed vs error {label}](speed_vs_error.png)", ""]
    return lines, summary


# ---------------------------------------------------------------------------- the README's generated block
# The README is hand-written but for one block between these markers (name: results), rewritten by --results from
# the crossover maps docs/results.md shows too (readme_results).
README_BEGIN = "<!-- generated: scripts/experiments_report.py --results: {} -->"
README_END = "<!-- end generated -->"
README_WIDTH = 115


class ReadmeError(ValueError):
    """A generated block's markers are missing, repeated or unknown in the README (a one-line message)."""


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _range(values: list[float], digits: int = 3) -> str:
    lo, hi = f"{min(values):.{digits}g}", f"{max(values):.{digits}g}"
    return lo if lo == hi else f"{lo}–{hi}"


CROSSOVER = "crossover_160x90"  # docs/results/<this>/map.json: scripts/crossover_map.py's output
ANIMATION = "animation_sun_160x90_thick_variants"  # scripts/bench_animation.py's output; its row `nrc`: the defaults


def crossover_summary(docs: Path, link: str = "[`docs/results.md`](docs/results.md)") -> str | None:
    """Where NRC pays off, in one paragraph, from the crossover map (``scripts/crossover_map.py``): NRC + OIDN over the
    path tracer + OIDN at equal time per frame along optical depth, per albedo; ``None`` without ``map.json``."""
    m = _read_json(docs / "results" / CROSSOVER / "map.json")
    pts = [p for p in (m or {}).get("points", []) if p.get("ratio_oidn") is not None]
    if not pts:
        return None
    size = "x".join(CROSSOVER.split("_")[-1].split("x"))
    text = (f"**Where NRC pays off** (the crossover map, {link}: the Disney cloud "
            f"under sun and sky, g 0.85, {size.replace('x', ' x ')}, single frames at equal time per frame after 30 "
            "warm-up frames, the denoiser's time included, floor-corrected relMSE over the cloud's pixels). "
            "NRC + OIDN's relMSE over the path tracer + OIDN's")
    parts = []
    for albedo in sorted({p["albedo"] for p in pts}):
        line = sorted((p for p in pts if p["albedo"] == albedo), key=lambda p: p["tau_median"])
        parts.append(f"at albedo {albedo:g}: " + ", ".join(f"{p['ratio_oidn']:.2g}x at optical depth "
                                                          f"{p['tau_median']:.0f}" for p in line))
    text += " is " + "; ".join(parts) + " (median optical depth of the camera rays that see the cloud)"
    raw = [p for p in pts if p.get("ratio_raw") is not None]
    if raw:
        text += f"; raw NRC over the raw path tracer {_range([p['ratio_raw'] for p in raw], 2)}x"
    means = [p["nrc_mean_ratio_medium"] for p in pts if p.get("nrc_mean_ratio_medium") is not None]
    if means:
        text += f"; NRC's image mean {_range(means)} of the reference's"
    warm = [p for p in ((_read_json(docs / "results" / (CROSSOVER + "_warm") / "map.json") or {}).get("points", []))
            if p.get("ratio_oidn") is not None]
    if warm:
        text += (". With a warm cache (150 warm-up frames): " + ", ".join(
            f"{p['ratio_oidn']:.2g}x at optical depth {p['tau_median']:.0f} (albedo {p['albedo']:g}, image mean "
            f"{fmt(p.get('nrc_mean_ratio_medium'), 3)})" for p in sorted(warm, key=lambda p: p["tau_median"])))
    for res, p in sorted(_other_sizes(docs).items()):
        text += (f". At {res.replace('x', ' x ')}: {p['ratio_oidn']:.2g}x at optical depth {p['tau_median']:.0f} "
                 f"(albedo {p['albedo']:g}, image mean {fmt(p.get('nrc_mean_ratio_medium'), 3)}; raw "
                 f"{fmt(p.get('ratio_raw'), 2)}x)")
    anim = _animation_row(docs)
    if anim is not None:
        a, r = anim
        scene = a["preset"] if a["preset"].startswith("the ") else f"`scene={a['preset']}`"
        text += (f". A whole {a['frames']}-frame animation of the turning sun ({scene}, every "
                 f"{a['scored_frames'][0] + 1}th frame scored, NRC from an untrained cache) takes NRC {r['whole_oidn_s']:.0f} s "
                 f"with OIDN, and its error is {r['ratio_vs_pt_oidn']:.2g}x the path tracer + OIDN's in the same "
                 f"whole-run time{' (extrapolated)' if r.get('extrapolated_oidn') else ''} (raw "
                 f"{r['ratio_vs_pt']:.2g}x)")
    wins = sorted((p for p in pts if p["ratio_oidn"] < 1), key=lambda p: p["tau_median"])
    if not wins:
        means = [p["nrc_mean_ratio_medium"] for p in pts if p.get("nrc_mean_ratio_medium") is not None]
        dark = bool(means) and max(means) < 0.97
        text += (". After 30 frames NRC + OIDN beats the path tracer + OIDN nowhere on the map: its remaining error is "
                 f"its cache's error{' (the image too dark)' if dark else ''}, which the denoiser cannot remove")
    elif len(wins) == len(pts):
        text += ". NRC + OIDN is ahead at every point"
    else:
        text += (f". NRC + OIDN is ahead at {len(wins)} of {len(pts)} points, from optical depth "
                 f"{wins[0]['tau_median']:.0f} (albedo {wins[0]['albedo']:g}) on")
    return text + "."


def _other_sizes(docs: Path) -> dict[str, dict]:
    """The crossover map's points at other image sizes (``docs/results/crossover_<W>x<H>/map.json`` beside
    :data:`CROSSOVER`), the thickest point of each."""
    out = {}
    for d in sorted((docs / "results").glob("crossover_*x*")):
        res = d.name.split("_", 1)[1]
        pts = [p for p in (_read_json(d / "map.json") or {}).get("points", []) if p.get("ratio_oidn") is not None]
        if d.name != CROSSOVER and "x" in res and res.replace("x", "").isdigit() and pts:
            out[res] = max(pts, key=lambda p: p["tau_median"])
    return out


def _animation_row(docs: Path) -> tuple[dict, dict] | None:
    """``(animation, NRC row)`` of :data:`ANIMATION`'s ``summary.json`` (``scripts/bench_animation.py``): the row of
    the configuration named ``nrc`` (the defaults), else the first NRC row; the animation gets ``preset``, the scene
    type its command named (``--preset``, else the default scene)."""
    summary = _read_json(docs / "results" / ANIMATION / "summary.json") or {}
    a = summary.get("animation")
    rows = [r for r in (a or {}).get("rows", []) if r.get("config") != "pt" and r.get("ratio_vs_pt_oidn")]
    if not rows:
        return None
    argv = (summary.get("meta") or {}).get("argv") or []
    preset = argv[argv.index("--preset") + 1] if "--preset" in argv[:-1] else "the default scene"
    return {**a, "preset": preset}, next((r for r in rows if r.get("config") == "nrc"), rows[0])


def crossover_section(docs: Path) -> list[str]:
    """The map's table and figure for docs/results.md (``[]`` without it)."""
    d = docs / "results" / CROSSOVER
    if not (d / "map.md").is_file():
        return []
    m = _read_json(d / "map.json") or {}
    out = ["## Where NRC pays off: the crossover map", "",
           f"Command (repo root): `python scripts/crossover_map.py {' '.join(m.get('argv') or [])}`; each point's "
           f"own speed-versus-error tables are in `docs/results/{CROSSOVER}/<point>/`.", "",
           (d / "map.md").read_text(), "", f"![crossover map](results/{CROSSOVER}/map.png)", ""]
    w = docs / "results" / (CROSSOVER + "_warm")
    if (w / "map.md").is_file():
        mw = _read_json(w / "map.json") or {}
        out += ["**A warm cache** (150 warm-up frames; command: `python scripts/crossover_map.py "
                f"{' '.join(mw.get('argv') or [])}`):", "", (w / "map.md").read_text(), ""]
    for res in _other_sizes(docs):
        d = docs / "results" / f"crossover_{res}"
        md = _read_json(d / "map.json") or {}
        out += [f"**At {res.replace('x', ' x ')}** (command: `python scripts/crossover_map.py "
                f"{' '.join(md.get('argv') or [])}`):", "", (d / "map.md").read_text(), ""]
    a = docs / "results" / ANIMATION
    if (a / "animation.md").is_file():
        ma = (_read_json(a / "summary.json") or {}).get("meta", {})
        out += ["**A whole animation** (the sun turning, from an untrained cache; every scored frame against its "
                "own reference; whole-run wall time, the path tracer's error read at NRC's whole-run time; command: "
                f"`python scripts/bench_animation.py {' '.join(ma.get('argv') or [])}`):", "",
                (a / "animation.md").read_text(), ""]
    return out


_NO_LINE_START = re.compile(r"[-+*>#|=]|\d+[.)]$")  # a line starting so would become a list, heading, ...


def _wrap(text: str, width: int = README_WIDTH) -> list[str]:
    """Greedy wrap that never starts a line with a word Markdown would read as a list item, heading or quote."""
    lines: list[str] = []
    for word in text.split():
        if lines and (len(lines[-1]) + 1 + len(word) <= width or _NO_LINE_START.match(word)):
            lines[-1] += " " + word
        else:
            lines.append(word)
    return lines


def _warmup_frames(m: dict) -> int:
    """The NRC warm-up frames of a crossover map (its command's ``--warmup``, else the tool's default, 30)."""
    argv = m.get("argv") or []
    return int(argv[argv.index("--warmup") + 1]) if "--warmup" in argv[:-1] else 30


def _points(m: dict | None) -> list[dict]:
    return [p for p in (m or {}).get("points", []) if p.get("ratio_oidn") is not None]


def readme_results(docs: Path) -> list[str]:
    """The README's generated block (``results``): what NRC found in one sentence, the crossover map's table (a row
    per point: optical depth, albedo, NRC + OIDN over the path tracer + OIDN at equal time per frame after the cold
    map's and the warm map's warm-up frames, NRC + OIDN's image mean over the reference's) and the map's figure,
    from ``docs/results/<CROSSOVER>/map.json`` and ``<CROSSOVER>_warm/map.json`` (``scripts/crossover_map.py``)."""
    cold_map = _read_json(docs / "results" / CROSSOVER / "map.json")
    warm_map = _read_json(docs / "results" / (CROSSOVER + "_warm") / "map.json")
    cold, warm = _points(cold_map), _points(warm_map)
    if not cold:
        return [f"(not measured: `docs/results/{CROSSOVER}/map.json` is missing; `python scripts/crossover_map.py "
                f"--out docs/results/{CROSSOVER}` writes it)"]
    size = CROSSOVER.split("_")[-1].replace("x", " x ")
    n_cold = _warmup_frames(cold_map)
    n_warm = _warmup_frames(warm_map) if warm else None

    def at(p: dict) -> str:
        return f"{p['ratio_oidn']:.2g}x at optical depth {p['tau_median']:.0f}"

    wins = sorted((p for p in cold if p["ratio_oidn"] < 1), key=lambda p: p["tau_median"])
    best = min(cold, key=lambda p: p["ratio_oidn"])
    worst = max(cold, key=lambda p: p["ratio_oidn"])
    text = (f"At equal time per frame ({size}, the denoiser's time included), NRC + OIDN's relMSE over the cloud "
            f"against the path tracer + OIDN's after {n_cold} warm-up frames from an untrained cache is ")
    if not wins:
        text += (f"higher at every point of the crossover map: from {at(best)} (albedo {best['albedo']:g}) to "
                 f"{at(worst)} (albedo {worst['albedo']:g})")
    else:
        text += (f"lower at {len(wins)} of {len(cold)} points, from optical depth {wins[0]['tau_median']:.0f} on "
                 f"(best {at(best)}), and up to {at(worst)} elsewhere")
    if warm:
        warm_wins = sorted((p for p in warm if p["ratio_oidn"] < 1), key=lambda p: p["tau_median"])
        if warm_wins:
            text += (f"; with a warm cache ({n_warm} frames) it wins at {len(warm_wins)} of the {len(warm)} points "
                     "measured: " + ", ".join(at(p) for p in warm_wins))
        else:
            text += f"; with a warm cache ({n_warm} frames) it still loses: " + ", ".join(at(p) for p in warm)
    raw = [p["ratio_raw"] for p in cold if p.get("ratio_raw") is not None]
    if raw:  # without a denoiser: the raw NRC frame against the raw path-traced one at equal time
        text += (f"; without a denoiser the raw NRC frame's relMSE is {min(raw):.2g}–{max(raw):.2g}x the raw path "
                 f"tracer's at equal time after {n_cold} frames")
    warm_of = {p["point"]: p for p in warm}
    rows = [f"| point | optical depth | albedo | NRC+OIDN / PT+OIDN, {n_cold} frames | "
            f"NRC+OIDN / PT+OIDN, {n_warm or 'more'} frames (warm) | NRC / PT raw, {n_cold} frames | "
            f"NRC+OIDN image mean / reference's, {n_cold} frames |",
            "|---|---:|---:|---:|---:|---:|---:|"]
    for p in sorted(cold, key=lambda p: (p["albedo"], p["tau_median"])):
        w = warm_of.get(p["point"])
        rows.append(f"| {p['point']} | {p['tau_median']:.0f} | {p['albedo']:g} | {p['ratio_oidn']:.2g} | "
                    f"{fmt(w and w['ratio_oidn'], 2)} | {fmt(p.get('ratio_raw'), 2)} | "
                    f"{fmt(p.get('nrc+oidn_mean_ratio_medium'), 3)} |")
    figure = f"[![Where NRC pays off: the crossover map](docs/results/{CROSSOVER}/map.png)](docs/results.md)"
    return [*_wrap(text + " (below 1: NRC wins)."), "", *rows, "", figure]


def rewrite_readme(text: str, blocks: dict[str, list[str]], where: str = "README.md") -> str:
    """``text`` with the lines between each block's markers replaced by the block (markers and every other line
    kept); :class:`ReadmeError` (one line) when a marker is missing, repeated, unknown or unclosed."""
    lines = text.split("\n")
    prefix = README_BEGIN.split("{}")[0]
    for i, line in enumerate(lines):
        if line.strip().startswith(prefix) and line.strip() not in {README_BEGIN.format(n) for n in blocks}:
            raise ReadmeError(f"{where}:{i + 1}: unknown generated block `{line.strip()}`; known: "
                              + ", ".join(f"`{README_BEGIN.format(n)}`" for n in blocks))
    for name, block in blocks.items():
        begin = README_BEGIN.format(name)
        starts = [i for i, line in enumerate(lines) if line.strip() == begin]
        if not starts:
            raise ReadmeError(f"{where}: no line `{begin}` (the generated {name} block goes between it and "
                              f"`{README_END}`)")
        if len(starts) > 1:
            raise ReadmeError(f"{where}: `{begin}` appears {len(starts)} times (lines "
                              f"{', '.join(str(i + 1) for i in starts)})")
        i = starts[0]
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() in (README_END,)
                    or lines[j].strip().startswith(prefix)), None)
        if end is None or lines[end].strip() != README_END:
            raise ReadmeError(f"{where}:{i + 1}: `{begin}` has no `{README_END}` after it")
        lines[i + 1:end] = ["", *block, ""]
    return "\n".join(lines)


def assemble_results(docs: Path, intro: Path | None) -> Path:
    """``docs/results.md``, a summary a reader finishes in minutes: where NRC pays off (the crossover map), the
    headline and the table over scene types, then one line per run linking to its own page (written here,
    ``docs/results/<run>/README.md``), the thesis experiments' pages and the hand-written discussion (``intro``,
    linked, not copied)."""
    lines = ["# Results", "",
             "Generated by `python scripts/experiments_report.py --results` from the outputs of "
             "`scripts/speed_vs_error.py` and `scripts/crossover_map.py` (under `docs/results/`). Each run's page names the command that reproduces it and the time it "
             "took.", ""]
    summaries: dict[str, tuple[str, dict]] = {}
    runs = []
    for label, name in SPEED_RUNS:
        page, summary = _speed_section(docs, label, name)
        if summary is None:
            runs.append(f"- {label}: not run (`docs/results/{name}/summary.json` is missing)")
            continue
        (docs / "results" / name / "README.md").write_text("\n".join(page))
        summaries[name] = (label, summary)
        runs.append(f"- [{label}](results/{name}/README.md)")
    cross = crossover_summary(docs, link="its section below")
    lines += ([cross, ""] if cross else []) + headline(summaries) + scene_type_table(summaries)
    if intro is not None and intro.is_file():
        rel = os.path.relpath(intro, docs)
        lines += [f"What these numbers mean, what changed and what is left: [`{rel}`]({rel}) (hand-written).", ""]
    lines += crossover_section(docs)
    lines += ["## Speed versus error: the runs", "", *runs, "", "## The theses' experiments", "",
              "Every experiment of Fedotov 2024 and Spindler 2022 a CPU can run, at the theses' own settings, each "
              "with a verdict: [`docs/theses/README.md`](theses/README.md) (`scripts/theses.py`)."]
    out = docs / "results.md"
    out.write_text("\n".join(lines) + "\n")
    return out


def run_reports(args: Any) -> Any:
    """``docs/results.md`` and the README's generated block (``--results``; options in ``args``); returns 0."""
    if not args.results:
        raise SystemExit("experiments_report: nothing to do without --results (the thesis experiments are "
                         "scripts/theses.py now)")
    readme = args.readme or args.docs.resolve().parent / "README.md"
    readme_text = new_readme = None
    if readme.is_file():  # checked before anything is written
        readme_text = readme.read_text()
        try:
            new_readme = rewrite_readme(readme_text, {"results": readme_results(args.docs)}, readme.name)
        except ReadmeError as e:
            raise SystemExit(f"experiments_report: {e}") from None
    (args.docs / "results").mkdir(parents=True, exist_ok=True)
    print(f"wrote {assemble_results(args.docs, args.intro)}")
    if new_readme is None:
        print(f"experiments_report: no {readme}; its generated block not rewritten")
    elif new_readme != readme_text:
        readme.write_text(new_readme)
        print(f"wrote {readme} (its generated block)")
    else:
        print(f"{readme}: its generated block unchanged")
    return 0


# ---------------------------------------------------------------------------- command line
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--docs", type=Path, default=REPO / "docs")
    p.add_argument("--results", action="store_true", help="assemble docs/results.md and rewrite the README's "
                   "generated block")
    p.add_argument("--readme", type=Path, default=None,
                   help="the README whose generated blocks --results rewrites (default: README.md beside --docs)")
    p.add_argument("--intro", type=Path, default=REPO / "docs" / "results_intro.md",
                   help="hand-written Markdown placed at the top of results.md (if it exists)")
    return p


def main(argv: list[str] | None = None) -> int:
    return run_reports(parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
