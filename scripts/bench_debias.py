"""Measurements of unbiased NRC (``renderer.debias``, :mod:`nrc.render.radiance_caching.debias`).

    python scripts/bench_debias.py blocks --out docs/results/debias_blocks
    python scripts/bench_debias.py moving --out docs/results/debias_moving_side_lit --preset side_lit

Two checks:

* :func:`blocks` -- **is it unbiased?** Accumulated NRC frames against Mitsuba 3 (an independent renderer), on
  small versions of the scene types of ``docs/results.md``: ``runs`` independent NRC runs (each ``frames``
  accumulated frames, the cache training from cold) and ``runs`` Mitsuba renders of ``mitsuba_spp`` spp, compared
  block-wise as the test suite compares renderers (block means within 4.5 standard errors, image means within 4;
  Welch's t over the runs), plus the per-pixel relative bias over the medium's pixels with its standard error, for
  each ``q`` (``q = 0``, the biased NRC, shows that the check can fail).
* :func:`moving` -- **per-frame error under a moving camera** (the orbit animation): NRC configurations warm up
  for ``warmup`` frames, then ``frames`` frames are scored against a reference of each frame's camera; the path
  tracer renders the same cameras at several spp, so each NRC row has the path tracer's (and the path tracer +
  OIDN's) error at the same time per frame (:func:`lab.analysis.baseline_error`, the rule of the
  equal-time ratios there).

Both write ``summary.json`` and a Markdown table into ``--out``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lab import REPO
from lab.analysis import baseline_error
from lab.machine import machine
from lab.per_frame import frame_reference, nrc_frames, pt_image, score
from lab.render import SEED_BASE, pt_warmup, setup
from lab.tables import write_result
from nrc.config import compose, preset, scene_hash
from nrc.evaluation.reference import REF_SEED
from nrc.metrics import medium_mask
from nrc.render.preview import medium_alpha
from nrc.scene import animated_scene


# ---------------------------------------------------------------------------- statistics
def block_z(a: list[np.ndarray], b: list[np.ndarray], block: int) -> np.ndarray:
    """Per-block, per-channel ``(mean_a - mean_b) / se`` of block-averaged images over independent renders."""
    def stats(ims: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        s = np.stack(ims).astype(np.float64)
        r, h, w, c = s.shape
        bl = s[:, :h // block * block, :w // block * block].reshape(r, h // block, block, w // block, block, c)
        per = bl.mean(axis=(2, 4))
        return per.mean(0), per.std(0, ddof=1) / math.sqrt(r)

    ma, sa = stats(a)
    mb, sb = stats(b)
    return (ma - mb) / np.maximum(np.sqrt(sa**2 + sb**2), 1e-6 * np.abs(mb).max())


def compare(ours: list[np.ndarray], theirs: list[np.ndarray], mask: np.ndarray, block: int,
            eps: float = 0.01) -> dict[str, Any]:
    """Block test (as ``tests/conftest.assert_images_agree``), image-mean ratio and the signed per-pixel relative
    bias over ``mask`` (``(mean a - mean b_1) / (|mean b_2| + eps)``, ``b_1``, ``b_2`` the two halves of ``theirs``:
    zero in expectation for an unbiased ``ours``) with standard errors (pixels taken as independent)."""
    z = block_z(ours, theirs, block)
    a, b = np.stack(ours).astype(np.float64), np.stack(theirs).astype(np.float64)
    ma, mb = np.array([im.mean() for im in a]), np.array([im.mean() for im in b])
    se_mean = math.sqrt((ma.var(ddof=1) + mb.var(ddof=1)) / len(a))
    z_mean = (ma.mean() - mb.mean()) / max(se_mean, 1e-30)
    # The per-pixel bias divides by a scale that is independent of both numerator terms: the first half of the
    # Mitsuba renders is the reference in the numerator, the second half the denominator. Dividing by a noisy
    # side that is also in the numerator biases the ratio (E[1/x] > 1/E[x]; our path tracer showed +14 % against
    # Mitsuba on the thin cloud's dim pixels), and so does a denominator holding the heavy-tailed side.
    h = len(b) // 2
    ref, scale = b[:h].mean(0), b[h:].mean(0)
    denom = np.abs(scale) + eps
    bias_px = (a.mean(0) - ref) / denom
    var_px = (a.var(0, ddof=1) / len(a) + b[:h].var(0, ddof=1) / h) / denom**2
    m = mask[..., None].repeat(3, -1) if mask is not None else np.ones_like(bias_px, bool)
    n = int(m.sum())
    return {
        "max_abs_z_block": float(np.abs(z).max()), "blocks": int(z.size),
        "z_mean": float(z_mean), "mean_ratio": float(ma.mean() / mb.mean()),
        "mean_ratio_se": float(se_mean / mb.mean()),
        "pixel_bias": float(bias_px[m].mean()), "pixel_bias_se": float(math.sqrt(var_px[m].sum()) / n),
        "pass": bool(np.abs(z).max() < 4.5 and abs(z_mean) < 4),
    }


# ---------------------------------------------------------------------------- runs
def blocks(presets: dict[str, list[str]], qs: list[Any], runs: int, frames: int, mitsuba_spp: int,
           extra: list[str], block: int, log: Any = print, save: Path | None = None) -> list[dict[str, Any]]:
    """The block check (module docstring) for every preset and ``q`` (``"pt"``: our path tracer, the control)."""
    from nrc.evaluation.mitsuba_bridge import render_mitsuba

    rows = []
    for name, overrides in presets.items():
        base = [*overrides, *extra]
        pt = setup(["renderer=pt", *base])
        cfg, scene = pt.cfg, pt.scene
        t0 = time.perf_counter()
        theirs = [render_mitsuba(scene, spp=mitsuba_spp, seed=REF_SEED + s)[0] for s in range(runs)]
        t_mts = time.perf_counter() - t0
        mask = medium_mask(medium_alpha(scene))
        for q in qs:
            t0 = time.perf_counter()
            if q == "pt":  # the control: our path tracer at the spp of the accumulated NRC frames
                ours = [pt_image(cfg, scene, frames * int(scene.integrator.spp), SEED_BASE + r)[0]
                        for r in range(runs)]
            else:
                nrc = setup(["renderer=nrc", *base, f"renderer.debias.probability={q}",
                             "renderer.log.tensorboard=false", "renderer.checkpoint_every=0"])
                ours = [nrc_frames(nrc.cfg, nrc.scene, frames, SEED_BASE + r, accumulate=True)[2]
                        for r in range(runs)]
            if save is not None:  # the renders, for other statistics later
                save.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(save / f"{name}_{q}.npz", ours=np.stack(ours).astype(np.float32),
                                    theirs=np.stack(theirs).astype(np.float32), mask=mask)
            row = {"scene": name, "q": q, "runs": runs, "frames": frames, "mitsuba_spp": mitsuba_spp,
                   "time_nrc_s": time.perf_counter() - t0, "time_mitsuba_s": t_mts,
                   **compare(ours, theirs, mask, block)}
            rows.append(row)
            log(row)
    return rows


def moving(preset: list[str], configs: dict[str, list[str]], pt_spp: list[int], warmup: int, frames: int,
           repeats: int, ref_spp: int, ref_chunk: int, ref_dir: Path, log: Any = print) -> dict[str, Any]:
    """The moving-camera check (module docstring)."""
    anim = ["renderer.animate.mode=orbit"]
    deg = float(compose(["renderer=nrc", *preset, *anim]).renderer.animate.degrees_per_frame)
    scored = range(warmup, warmup + frames)
    pt = setup(["renderer=pt", *preset, "renderer.backend=compiled"])
    pcfg, pscene = pt.cfg, pt.scene
    scenes = [animated_scene(pscene, "orbit", deg, f) for f in scored]  # the scored frames' cameras
    h = scene_hash(pcfg)[:12]
    refs, masks = [], []
    for f, s in zip(scored, scenes):
        t0 = time.perf_counter()
        refs.append(frame_reference(pcfg, s, ref_spp, ref_chunk, ref_dir / f"moving_{h}_orbit{f}_{ref_spp}spp.exr"))
        masks.append(medium_mask(medium_alpha(s)))
        log(f"reference of frame {f}: {time.perf_counter() - t0:.1f} s")
    rows: list[dict[str, Any]] = []
    pt_warmup(pscene, pcfg)  # compile / first-use costs, untimed
    for spp in pt_spp:
        ims, ts = [], []
        for rep in range(repeats):
            for k, s in enumerate(scenes):
                img, dt = pt_image(pcfg, s, spp, SEED_BASE + 97 * rep + k)
                ims.append(img)
                ts.append(dt)
        row = {"config": "pt", "spp": spp, "time_s": float(np.median(ts)), **score(ims, refs * repeats, masks * repeats)}
        rows.append(row)
        log(row)
    for name, overrides in configs.items():
        nrc = setup(["renderer=nrc", *preset, *anim, *overrides, "renderer.log.tensorboard=false",
                     "renderer.checkpoint_every=0"])
        ims, ts = [], []
        for rep in range(repeats):
            im, t, _, _ = nrc_frames(nrc.cfg, nrc.scene, warmup + frames, SEED_BASE + 7919 * rep, keep=scored)
            ims += im
            ts += t
        row = {"config": name, "spp": int(nrc.cfg.scene.integrator.spp), "time_s": float(np.median(ts)),
               **score(ims, refs * repeats, masks * repeats)}
        rows.append(row)
        log(row)
    add_baseline(rows)
    return {"rows": rows, "scored_frames": list(scored), "ref_spp": ref_spp}


def add_baseline(rows: list[dict[str, Any]]) -> None:
    """The path tracer's (and the path tracer + OIDN's) error at each NRC row's time per frame."""
    for tag in ("", "_oidn"):
        points = [(r["time_s"], r["rel_mse_medium" + tag]) for r in rows if r["config"] == "pt"]
        for r in rows:
            if r["config"] != "pt":
                pt_err = baseline_error(points, r["time_s"])
                r["pt_rel_mse_medium" + tag] = pt_err
                r["ratio_vs_pt" + tag] = r["rel_mse_medium" + tag] / pt_err


def markdown_blocks(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene | q | runs x frames | Mitsuba spp | max block |z| (blocks) | image mean z | mean / Mitsuba | "
             "per-pixel rel. bias | pass |", "|---|---:|---:|---:|---:|---:|---:|---:|:---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['q']} | {r['runs']} x {r['frames']} | {r['mitsuba_spp']} | "
                     f"{r['max_abs_z_block']:.2f} ({r['blocks']}) | {r['z_mean']:+.2f} | "
                     f"{r['mean_ratio']:.4f} ± {r['mean_ratio_se']:.4f} | "
                     f"{r['pixel_bias']:+.4f} ± {r['pixel_bias_se']:.4f} | {'yes' if r['pass'] else '**no**'} |")
    return "\n".join(lines) + "\n"


def markdown_moving(result: dict[str, Any]) -> str:
    lines = ["| config | spp/frame | s/frame | relMSE medium | mean/ref | relMSE + OIDN | mean/ref + OIDN | "
             "clamp bias | pt at that time | pt + OIDN at that time |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        pt = "–" if r["config"] == "pt" else f"{r['pt_rel_mse_medium']:.4g} ({r['ratio_vs_pt']:.2f}x)"
        pto = "–" if r["config"] == "pt" else f"{r['pt_rel_mse_medium_oidn']:.4g} ({r['ratio_vs_pt_oidn']:.2f}x)"
        lines.append(f"| {r['config']} | {r['spp']} | {r['time_s']:.3f} | {r['rel_mse_medium']:.4g} | "
                     f"{r['mean_ratio_medium']:.3f} | {r['rel_mse_medium_oidn']:.4g} | {r['mean_ratio_medium_oidn']:.3f} | "
                     f"{r['clamp_bias']:+.4f} | {pt} | {pto} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- command line
def sized(name: str, width: int, height: int) -> list[str]:
    keep = [o for o in preset(name) if not o.startswith(("scene.camera.width=", "scene.camera.height="))]
    return [*keep, f"scene.camera.width={width}", f"scene.camera.height={height}"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("check", choices=["blocks", "moving"])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--presets", default="side_lit,back_lit_thin,point_below", help="blocks: scene types")
    p.add_argument("--preset", default="side_lit", help="moving: the scene type")
    p.add_argument("--width", type=int, default=None, help="image width (blocks 48, moving 160)")
    p.add_argument("--height", type=int, default=None, help="image height (blocks 27, moving 90)")
    p.add_argument("--q", default="pt,0,0.2", help="blocks: debias probabilities (pt: the path tracer, the control)")
    p.add_argument("--runs", type=int, default=8, help="blocks: independent runs per side")
    p.add_argument("--frames", type=int, default=None, help="blocks: accumulated frames (32); moving: scored (4)")
    p.add_argument("--mitsuba-spp", type=int, default=256)
    p.add_argument("--block", type=int, default=8, help="blocks: block edge in pixels")
    p.add_argument("--config", action="append", default=[], metavar="NAME=OV1,OV2",
                   help="moving: an NRC configuration (default: biased and q=0.2)")
    p.add_argument("--pt-spp", default="1,2,4,8,16", help="moving: path tracer spp per frame")
    p.add_argument("--warmup", type=int, default=30, help="moving: NRC frames before scoring")
    p.add_argument("--repeats", type=int, default=2, help="moving: independent runs")
    p.add_argument("--ref-spp", type=int, default=1024, help="moving: spp of each frame's reference")
    p.add_argument("--ref-chunk", type=int, default=64)
    p.add_argument("--save", type=Path, default=None, help="blocks: write the renders (npz) into this folder")
    p.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = p.parse_intermixed_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    argv_used = list(sys.argv[1:] if argv is None else argv)
    if "--save" in argv_used:  # a folder of this machine's, not part of the result
        i = argv_used.index("--save")
        del argv_used[i:i + 2]
    meta = {"argv": argv_used, "machine": machine()}
    if args.check == "blocks":
        w, h = args.width or 48, args.height or 27
        presets = {name: sized(name, w, h) for name in args.presets.split(",")}
        rows = blocks(presets, [q if q == "pt" else float(q) for q in args.q.split(",")], args.runs, args.frames or 32,
                         args.mitsuba_spp, args.overrides, args.block, save=args.save)
        table = markdown_blocks(rows)
        write_result(args.out, "blocks", rows, table, meta)
    else:
        w, h = args.width or 160, args.height or 90
        configs = {name: ovs.split(",") for name, ovs in (c.split("=", 1) for c in args.config)} or {
            "nrc": ["scene.integrator.spp=1"], "nrc_debias_0.2": ["scene.integrator.spp=1",
                                                                  "renderer.debias.probability=0.2"]}
        res = moving([*sized(args.preset, w, h), *args.overrides], configs,
                        [int(s) for s in args.pt_spp.split(",")], args.warmup, args.frames or 4, args.repeats,
                        args.ref_spp, args.ref_chunk, REPO / "data" / "references")
        table = markdown_moving(res)
        write_result(args.out, "moving", res, table, meta)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
