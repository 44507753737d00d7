"""A whole animation, NRC against the path tracer: every frame rendered from a cold start, whole-run wall time
beside the error of every ``--score-every``-th frame against its own reference.

    python scripts/bench_animation.py --out docs/results/animation_sun_160x90_thick --preset thick \\
        --frames 60 --score-every 10 --mode sun --pt-spp 1,2,4

A ``--frames``-long animation (``renderer.animate.mode``: ``sun`` turns the directional lights, ``orbit`` the
camera; :func:`nrc.scene.animated_scene`) rendered from a cold start by each NRC configuration and by the path
tracer at several spp per frame, every ``--score-every``-th frame scored against its own reference. The comparison
is of **whole runs**: each side's wall time for all frames -- the path tracer's first-use cost (loading or
compiling its step) and NRC's (its step, its untrained first frames) included, the denoiser's time per frame added
to both for the denoised rows -- and the mean error over the scored frames; the path tracer's error at NRC's
whole-run time is read off its measured points (:func:`lab.analysis.baseline_error`, ``extrapolated`` set when
NRC's time lies outside them). Process start-up (importing torch, composing the config) is the same for both and
not counted.

Writes ``summary.json`` and ``animation.md`` into ``--out``; references are kept in ``data/references``.
"""

from __future__ import annotations

import argparse
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
from nrc.config import PRESETS, compose, preset, scene_hash
from nrc.metrics import medium_mask
from nrc.render.preview import medium_alpha
from nrc.scene import animated_scene


def animation(preset: list[str], configs: dict[str, list[str]], pt_spp: list[int], frames: int, score_every: int,
              mode: str, ref_spp: int, ref_chunk: int, ref_dir: Path, log: Any = print,
              nrc_seed: int = SEED_BASE) -> dict[str, Any]:
    """The whole-run comparison (module docstring); rows per configuration with ``whole_s`` (wall time of all
    frames), ``whole_oidn_s`` (plus the denoiser on every frame) and the scores of the scored frames. ``nrc_seed``:
    the NRC runs' seed (another seed, another draw of the same configuration; the path tracer's stay)."""
    anim = [f"renderer.animate.mode={mode}"]
    pt = setup(["renderer=pt", "renderer.backend=compiled", *preset])  # the preset may choose another backend
    pcfg, pscene = pt.cfg, pt.scene
    deg = float(compose(["renderer=nrc", *preset, *anim]).renderer.animate.degrees_per_frame)
    scenes = [animated_scene(pscene, mode, deg, f) for f in range(frames)]
    scored = list(range(score_every - 1, frames, score_every))
    h = scene_hash(pcfg)[:12]
    refs, masks = [], []
    for f in scored:
        t0 = time.perf_counter()
        refs.append(frame_reference(pcfg, scenes[f], ref_spp, ref_chunk,
                                    ref_dir / f"anim_{h}_{mode}{deg:g}_f{f}_{ref_spp}spp.exr"))
        masks.append(medium_mask(medium_alpha(scenes[f])))
        log(f"reference of frame {f}: {time.perf_counter() - t0:.1f} s")
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    pt_warmup(pscene, pcfg)  # the step's first use (loading its package or compiling): part of the whole run
    first_use = time.perf_counter() - t0
    for spp in pt_spp:
        ims, ts = [], []
        for f, s in enumerate(scenes):
            img, dt = pt_image(pcfg, s, spp, SEED_BASE + 97 * spp + f)
            ts.append(dt)
            if f in scored:
                ims.append(img)
        rows.append({"config": "pt", "spp": spp, "whole_s": first_use + float(np.sum(ts)),
                     "frame_s": float(np.median(ts)), "first_use_s": first_use, **score(ims, refs, masks)})
        log(rows[-1])
    for name, overrides in configs.items():
        t0 = time.perf_counter()  # NRC's scene load counted in its whole run, as before
        run = setup(["renderer=nrc", *preset, *anim, *overrides, "renderer.log.tensorboard=false",
                     "renderer.checkpoint_every=0"])
        cfg = run.cfg
        ims, ts, _, _ = nrc_frames(cfg, run.scene, frames, nrc_seed, keep=scored)
        whole = time.perf_counter() - t0
        rows.append({"config": name, "spp": int(cfg.scene.integrator.spp), "whole_s": whole,
                     "frame_s": float(np.median(ts)), **score(ims, refs, masks)})
        log(rows[-1])
    for r in rows:
        r["whole_oidn_s"] = r["whole_s"] + frames * r["oidn_s"]
    for tag, clock in (("", "whole_s"), ("_oidn", "whole_oidn_s")):
        points = [(r[clock], r["rel_mse_medium" + tag]) for r in rows if r["config"] == "pt"]
        lo, hi = min(p[0] for p in points), max(p[0] for p in points)
        for r in rows:
            if r["config"] != "pt":
                r["pt_rel_mse_medium" + tag] = baseline_error(points, r[clock])
                r["ratio_vs_pt" + tag] = r["rel_mse_medium" + tag] / r["pt_rel_mse_medium" + tag]
                r["extrapolated" + tag] = not lo <= r[clock] <= hi
    return {"rows": rows, "frames": frames, "scored_frames": scored, "mode": mode, "degrees_per_frame": deg,
            "ref_spp": ref_spp}


def markdown(result: dict[str, Any]) -> str:
    """The result as a Markdown table."""
    lines = ["| config | spp/frame | whole run (s) | + OIDN (s) | s/frame | relMSE medium | mean/ref | relMSE + OIDN | "
             "mean/ref + OIDN | pt at that whole time | pt + OIDN at that whole time |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        def vs(tag: str) -> str:
            if r["config"] == "pt":
                return "–"
            flag = " (extrapolated)" if r["extrapolated" + tag] else ""
            return f"{r['pt_rel_mse_medium' + tag]:.4g} (**{r['ratio_vs_pt' + tag]:.2f}x**){flag}"
        lines.append(f"| {r['config']} | {r['spp']} | {r['whole_s']:.1f} | {r['whole_oidn_s']:.1f} | "
                     f"{r['frame_s']:.3f} | {r['rel_mse_medium']:.4g} | {r['mean_ratio_medium']:.3f} | "
                     f"{r['rel_mse_medium_oidn']:.4g} | {r['mean_ratio_medium_oidn']:.3f} | {vs('')} | {vs('_oidn')} |")
    return "\n".join(lines) + "\n"



def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--preset", default="thick", choices=PRESETS, help="the scene type (conf/scene/)")
    p.add_argument("--mode", default="sun", choices=["sun", "orbit"], help="renderer.animate.mode")
    p.add_argument("--frames", type=int, default=60, help="frames of the animation")
    p.add_argument("--score-every", type=int, default=10, help="score frames k-1, 2k-1, ...")
    p.add_argument("--pt-spp", default="1,2,4", help="path tracer spp per frame")
    p.add_argument("--config", action="append", default=[], metavar="NAME=OV1,OV2",
                   help="an NRC configuration (default: nrc=renderer.backend=compiled)")
    p.add_argument("--ref-spp", type=int, default=512, help="spp of each scored frame's reference")
    p.add_argument("--ref-chunk", type=int, default=64)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--nrc-seed", type=int, default=SEED_BASE,
                   help="the NRC runs' seed (scene.integrator.seed does not reach them)")
    p.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = p.parse_intermixed_args(argv)
    if args.frames < args.score_every or args.score_every < 1:
        p.error("--score-every must be between 1 and --frames")
    if args.threads:
        torch.set_num_threads(args.threads)
    configs = {name: ovs.split(",") for name, ovs in (c.split("=", 1) for c in args.config)} or {
        "nrc": ["renderer.backend=compiled"]}
    res = animation([*preset(args.preset), *args.overrides], configs,
                              [int(s) for s in args.pt_spp.split(",")], args.frames, args.score_every, args.mode,
                              args.ref_spp, args.ref_chunk, REPO / "data" / "references", nrc_seed=args.nrc_seed)
    table = markdown(res)
    meta = {"argv": list(sys.argv[1:] if argv is None else argv), "machine": machine()}
    write_result(args.out, "animation", res, table, meta)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
