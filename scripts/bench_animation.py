"""A whole animation, NRC against the path tracer: every frame rendered from a cold start, whole-run wall time
beside the error of every ``--score-every``-th frame against its own reference (:mod:`nrc.evaluation.animation`).

    python scripts/bench_animation.py --out docs/results/animation_sun_160x90_thick --preset thick \\
        --frames 60 --score-every 10 --mode sun --pt-spp 1,2,4

Writes ``summary.json`` and ``animation.md`` into ``--out``; references are kept in ``data/references``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from nrc.evaluation import animation, debias_bench as db
from nrc.evaluation.speed_vs_error import PRESETS, preset


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
    p.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = p.parse_intermixed_args(argv)
    if args.frames < args.score_every or args.score_every < 1:
        p.error("--score-every must be between 1 and --frames")
    if args.threads:
        torch.set_num_threads(args.threads)
    configs = {name: ovs.split(",") for name, ovs in (c.split("=", 1) for c in args.config)} or {
        "nrc": ["renderer.backend=compiled"]}
    res = animation.animation([*preset(args.preset), *args.overrides], configs,
                              [int(s) for s in args.pt_spp.split(",")], args.frames, args.score_every, args.mode,
                              args.ref_spp, args.ref_chunk, db.REPO / "data" / "references")
    table = animation.markdown(res)
    meta = {"argv": list(sys.argv[1:] if argv is None else argv), "machine": db.machine()}
    db.write(args.out, "animation", res, table, meta)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
