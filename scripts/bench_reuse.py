"""Reservoir reuse (``renderer.reuse.mode``) against none: 1-spp frames of the path tracer, raw and denoised.

For each scene type, ``--frames`` 1-spp frames of a static camera are rendered per mode in one process:
``none`` as independent 1-spp renders (seeds), ``spatial`` and ``spatiotemporal`` as the passes of one
``spp = frames`` render (``PathTracer.render(on_pass=...)``; temporal reuse chains the passes). Each frame is
scored against a converged reference (``--ref-spp``, rendered once with ``none`` and kept in ``--out``):
relMSE (medium pixels), the image mean over the reference's (bias), HDR-FLIP, and the same after Intel Open
Image Denoise (``pyoidn``). Frames before ``--warmup`` are left out of the means (temporal reuse needs a few
frames of history). Seconds per frame: the median over frames (with reuse, each pass's trace + reuse pass;
``none``: the render call). Equal time: the ``none`` relMSE at a reuse frame's time is its 1-spp relMSE scaled
by ``t_none / t_reuse`` (raw: relMSE of an unbiased estimator falls as 1 / samples), and ``none`` is also
rendered at ``ceil(t_reuse / t_none)`` spp for the denoised comparison at equal time (OIDN does not scale so).

    python scripts/bench_reuse.py [--scenes many_lights,side_lit] [--frames 12] [--warmup 4]
        [--out outputs/bench_reuse] [--extra renderer.reuse.neighbors=4 ...] [--nrc many_lights]

``--nrc`` scene types also run ``renderer=nrc`` frames of the static camera (``none`` against
``spatiotemporal``; the reference must exist, i.e. the scene was in ``--scenes`` once).

Writes ``bench.json`` and ``bench.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from nrc.config import code_version, compose  # noqa: E402
from nrc.evaluation.metrics import hdr_flip, medium_mask, rel_mse  # noqa: E402
from nrc.evaluation.reference import medium_alpha  # noqa: E402
from nrc.evaluation.speed_vs_error import PRESETS  # noqa: E402
from nrc.render.pt import PathTracer  # noqa: E402
from nrc.scene import load_scene  # noqa: E402

MODES = ("none", "spatial", "spatiotemporal")
COMMON = ["renderer=pt", "renderer.backend=eager", "renderer.light_selection=ris"]


def render(overrides: list[str], on_pass=None):
    cfg = compose(overrides)
    scene = load_scene(cfg.scene)
    t0 = time.perf_counter()
    res = PathTracer(scene, cfg).render(on_pass=on_pass)
    return res, time.perf_counter() - t0, scene


def score(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    from nrc.denoise import denoise

    den = denoise(img)
    return {"rel_mse": rel_mse(img, ref, mask), "mean_ratio": float(img.mean() / ref.mean()),
            "flip": hdr_flip(img, ref), "rel_mse_oidn": rel_mse(den, ref, mask),
            "mean_ratio_oidn": float(den.mean() / ref.mean()), "flip_oidn": hdr_flip(den, ref)}


def bench_scene(name: str, args, log) -> dict:
    base = [*PRESETS[name], *COMMON, *args.extra]
    ref_path = args.out / f"ref_{name}_{args.ref_spp}.npy"
    if ref_path.is_file():
        ref = np.load(ref_path)
    else:
        log(f"{name}: reference, {args.ref_spp} spp")
        res, secs, _ = render([*base, f"scene.integrator.spp={args.ref_spp}", "scene.integrator.seed=900001"])
        ref = res.image
        np.save(ref_path, ref)
        log(f"  {secs:.0f} s")
    cfg = compose(base)
    mask = medium_mask(medium_alpha(load_scene(cfg.scene)))
    out: dict = {"scene": name, "overrides": base, "modes": {}}
    for mode in MODES:
        frames, times = [], []
        if mode == "none":
            for f in range(args.frames):
                res, secs, _ = render([*base, "scene.integrator.spp=1", f"scene.integrator.seed={f + 1}"])
                frames.append(res.image)
                times.append(res.metrics["time_render_s"])
        else:
            stamps = [time.perf_counter()]

            def on_pass(j, img):
                frames.append(img.cpu().numpy().copy())
                stamps.append(time.perf_counter())

            res, secs, _ = render([*base, f"renderer.reuse.mode={mode}", f"scene.integrator.spp={args.frames}",
                                   "scene.integrator.seed=1"], on_pass)
            times = list(np.diff(stamps))
            out.setdefault("reuse_metrics", {})[mode] = {k: v for k, v in res.metrics.items() if k.startswith("reuse")}
        scores = [score(f, ref, mask) for f in frames[args.warmup:]]
        row = {k: float(np.mean([s[k] for s in scores])) for k in scores[0]}
        row["seconds_per_frame"] = float(np.median(times[args.warmup:] if mode != "none" else times))
        out["modes"][mode] = row
        log(f"{name} {mode}: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()))
    t_none = out["modes"]["none"]["seconds_per_frame"]
    for mode in MODES[1:]:
        row = out["modes"][mode]
        k = max(1, math.ceil(row["seconds_per_frame"] / t_none - 0.05))
        eq = []
        for f in range(args.equal_time_frames):
            res, _, _ = render([*base, f"scene.integrator.spp={k}", f"scene.integrator.seed={1000 + f}"])
            eq.append(score(res.image, ref, mask))
        row["equal_time_spp_none"] = k
        row["none_rel_mse_at_equal_time"] = out["modes"]["none"]["rel_mse"] * t_none / row["seconds_per_frame"]
        row["none_rel_mse_oidn_at_equal_time"] = float(np.mean([s["rel_mse_oidn"] for s in eq]))
        row["gain_raw_equal_time"] = row["none_rel_mse_at_equal_time"] / row["rel_mse"]
        row["gain_oidn_equal_time"] = row["none_rel_mse_oidn_at_equal_time"] / row["rel_mse_oidn"]
        log(f"{name} {mode}: equal-time gain raw {row['gain_raw_equal_time']:.2f}x, "
            f"OIDN {row['gain_oidn_equal_time']:.2f}x (none at {k} spp)")
    return out


def bench_nrc(name: str, args, log) -> dict:
    """NRC frames of a static camera (the reference of :func:`bench_scene`), reuse ``none`` against
    ``spatiotemporal``: per-frame relMSE, bias and the same after OIDN, frames after ``--nrc-warmup``."""
    from nrc.render.radiance_caching import NRCRenderer

    base = [*PRESETS[name], "renderer=nrc", "renderer.backend=eager", "renderer.light_selection=ris",
            "renderer.log.tensorboard=false", f"frames={args.nrc_frames}", *args.extra]
    ref = np.load(args.out / f"ref_{name}_{args.ref_spp}.npy")
    cfg = compose(base)
    mask = medium_mask(medium_alpha(load_scene(cfg.scene)))
    out: dict = {"scene": name, "renderer": "nrc", "overrides": base, "modes": {}}
    for mode in ("none", "spatiotemporal"):
        cfg = compose([*base, f"renderer.reuse.mode={mode}"])
        frames = []
        res = NRCRenderer(load_scene(cfg.scene), cfg).render(on_frame=lambda f, img, o, st: frames.append(img))
        scores = [score(f, ref, mask) for f in frames[args.nrc_warmup:]]
        row = {k: float(np.mean([sc[k] for sc in scores])) for k in scores[0]}
        row["seconds_per_frame"] = float(np.median(res.metrics["frame_times_s"][args.nrc_warmup:]))
        out["modes"][mode] = row
        log(f"nrc {name} {mode}: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()))
    st, no = out["modes"]["spatiotemporal"], out["modes"]["none"]
    st["gain_raw_equal_time"] = no["rel_mse"] * no["seconds_per_frame"] / (st["rel_mse"] * st["seconds_per_frame"])
    st["gain_oidn_per_frame"] = no["rel_mse_oidn"] / st["rel_mse_oidn"]
    return out


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"# Reservoir reuse: 1-spp frames ({meta['frames']} frames, first {meta['warmup']} left out)", "",
             f"{meta['machine']}; torch {meta['torch']}; code {meta['code']}; extra: {' '.join(meta['extra']) or '-'}", "",
             "| scene | mode | s/frame | relMSE | mean/ref | FLIP | relMSE OIDN | mean/ref OIDN | FLIP OIDN | "
             "equal-time gain raw | equal-time gain OIDN |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        for mode, row in r["modes"].items():
            g1 = row.get("gain_raw_equal_time")
            if "gain_oidn_per_frame" in row:  # nrc: no equal-time none render
                g2 = f"{row['gain_oidn_per_frame']:.2f}x per frame"
            elif "gain_oidn_equal_time" in row:
                g2 = f"{row['gain_oidn_equal_time']:.2f}x (none at {row['equal_time_spp_none']} spp)"
            else:
                g2 = "-"
            lines.append(f"| {r['scene']} ({r.get('renderer', 'pt')}) | {mode} | {row['seconds_per_frame']:.3f} | "
                         f"{row['rel_mse']:.4g} | {row['mean_ratio']:.4f} | {row['flip']:.4f} | "
                         f"{row['rel_mse_oidn']:.4g} | {row['mean_ratio_oidn']:.4f} | {row['flip_oidn']:.4f} | "
                         f"{'-' if g1 is None else f'{g1:.2f}x'} | {g2} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="many_lights,side_lit")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--equal-time-frames", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=512)
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "bench_reuse")
    ap.add_argument("--extra", nargs="*", default=[])
    ap.add_argument("--nrc", default="", help="scene types to run NRC frames on too (static camera)")
    ap.add_argument("--nrc-frames", type=int, default=16)
    ap.add_argument("--nrc-warmup", type=int, default=8)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(msg, flush=True)

    results = [bench_scene(s, args, log) for s in args.scenes.split(",") if s]
    results += [bench_nrc(s, args, log) for s in args.nrc.split(",") if s]
    meta = {"frames": args.frames, "warmup": args.warmup, "extra": args.extra, "code": code_version(),
            "torch": torch.__version__, "machine": f"{platform.machine()}, {torch.get_num_threads()} threads"}
    (args.out / "bench.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    (args.out / "bench.md").write_text(markdown(results, meta))
    print(markdown(results, meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
