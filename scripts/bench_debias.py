"""Unbiased NRC (``renderer.debias``): block tests against Mitsuba after accumulation, and per-frame error under a
moving camera (command line of :mod:`nrc.evaluation.debias_bench`).

    python scripts/bench_debias.py blocks --out docs/results/debias_blocks
    python scripts/bench_debias.py moving --out docs/results/debias_moving_side_lit --preset side_lit
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from nrc.evaluation import debias_bench as db
from nrc.evaluation.speed_vs_error import preset


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
    meta = {"argv": argv_used, "machine": db.machine()}
    if args.check == "blocks":
        w, h = args.width or 48, args.height or 27
        presets = {name: sized(name, w, h) for name in args.presets.split(",")}
        rows = db.blocks(presets, [q if q == "pt" else float(q) for q in args.q.split(",")], args.runs, args.frames or 32,
                         args.mitsuba_spp, args.overrides, args.block, save=args.save)
        table = db.markdown_blocks(rows)
        db.write(args.out, "blocks", rows, table, meta)
    else:
        w, h = args.width or 160, args.height or 90
        configs = {name: ovs.split(",") for name, ovs in (c.split("=", 1) for c in args.config)} or {
            "nrc": ["scene.integrator.spp=1"], "nrc_debias_0.2": ["scene.integrator.spp=1",
                                                                  "renderer.debias.probability=0.2"]}
        res = db.moving([*sized(args.preset, w, h), *args.overrides], configs,
                        [int(s) for s in args.pt_spp.split(",")], args.warmup, args.frames or 4, args.repeats,
                        args.ref_spp, args.ref_chunk, db.REPO / "data" / "references")
        table = db.markdown_moving(res)
        db.write(args.out, "moving", res, table, meta)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
