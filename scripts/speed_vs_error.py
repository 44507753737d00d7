"""Speed versus error: NRC against the path tracer at equal time. The runner, the Pareto / crossover analysis,
tables and plots live in :mod:`nrc.evaluation.speed_vs_error`; this is its command line.

    python scripts/speed_vs_error.py --help
    python scripts/speed_vs_error.py --out docs/results/speed_160x90 scene.camera.width=160 scene.camera.height=90
    python scripts/speed_vs_error.py --out outputs/sve --jobs slurm --slurm partition=cpu   # a configuration a job
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nrc.evaluation import speed_vs_error as sve


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=sve.REPO / "outputs" / "speed_vs_error")
    p.add_argument("--preset", choices=sve.PRESETS, default="disney", help="scene overrides applied first")
    p.add_argument("--mode", choices=["single", "accumulate", "both"], default="both")
    p.add_argument("--configs", default=",".join(sve.DEFAULT_CONFIGS), help="comma-separated names (see CONFIGS)")
    p.add_argument("--config", action="append", default=[], metavar="NAME=OV1,OV2", help="a custom configuration")
    p.add_argument("--pt-spp", default="1,2,4,8", help="pt spp per frame (single mode)")
    p.add_argument("--nrc-spp", default="1", help="NRC spp per frame (single mode)")
    p.add_argument("--repeats", type=int, default=3, help="independent pt frames per spp (single mode)")
    p.add_argument("--warmup", type=int, default=10, help="NRC training frames before scoring (single mode)")
    p.add_argument("--frames", type=int, default=4, help="scored NRC frames (single mode)")
    p.add_argument("--nrc-repeats", type=int, default=1,
                   help="independent NRC runs per configuration (single mode; their scored frames are pooled: the "
                        "spread between runs of the online training shows in the variance)")
    p.add_argument("--acc-max-frames", type=int, default=256, help="most frames accumulated (accumulate mode)")
    p.add_argument("--acc-nrc-frames", type=int, default=None,
                   help="NRC's frames in accumulate mode (default --acc-max-frames; scored there too), e.g. 30 with a "
                        "larger --acc-max-frames for the path tracer, which then runs until --acc-budget-s")
    p.add_argument("--acc-nrc-last", action="store_true",
                   help="also score NRC's frame alone at each accumulated point (config NAME:last): after a cold "
                        "start its running mean still holds the untrained cache's first frames")
    p.add_argument("--acc-budget-s", type=float, default=60.0, help="render seconds per sequence (accumulate)")
    p.add_argument("--acc-repeats", type=int, default=2, help="independent sequences (accumulate mode)")
    p.add_argument("--acc-pt-spp", type=int, default=4,
                   help="spp per accumulated pt frame (a wavefront frame costs about the same at 1-4 spp)")
    p.add_argument("--acc-nrc-spp", type=int, default=1, help="NRC spp per accumulated frame (accumulate mode)")
    p.add_argument("--acc-startup", action="store_true",
                   help="count start-up in the accumulated times (the process's imports and scene load, and each "
                        "configuration's warm-up: the compile or its load): the cold-start comparison a user waits for")
    p.add_argument("--acc-configs", default="pt,nrc_hashgrid",
                   help="configurations also run in accumulate mode (comma-separated; 'all' for every one)")
    p.add_argument("--nrc-overrides", default=",".join(sve.NRC_DEFAULTS),
                   help="Hydra overrides applied to every nrc configuration before its own (comma-separated)")
    p.add_argument("--denoise", action="store_true",
                   help="also score every configuration denoised by OIDN (single frames; accumulated: the running "
                        "mean at each point), time + denoise time")
    p.add_argument("--reference", type=Path, default=None)
    p.add_argument("--ref-spp", type=int, default=512)
    p.add_argument("--ref-chunk", type=int, default=64)
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    p.add_argument("--skip-missing", action="store_true", default=True,
                   help="skip configurations whose renderer is not available (default)")
    p.add_argument("--progress", action="store_true", help="progress bar for a reference render")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--jobs", choices=["none", "local", "slurm"], default="none",
                   help="run each configuration as its own launcher job (submitit; local: one after another, slurm: "
                        "a node each, --exclusive), then merge their rows (refusing mixed machine types)")
    p.add_argument("--slurm", action="append", default=[], metavar="KEY=VALUE",
                   help="a Slurm parameter of the jobs (partition=cpu, cpus_per_task=32, timeout_min=120, ...)")
    p.add_argument("--only", default=None, metavar="NAME",
                   help="run only this configuration and write its rows to OUT/configs/NAME.json (what a job runs)")
    p.add_argument("--replot", type=Path, default=None, metavar="DIR",
                   help="only rewrite the tables and plot of DIR/summary.json (no rendering)")
    return p


def main(argv: list[str] | None = None) -> int:
    args, overrides = parser().parse_known_args(argv)
    if args.replot:
        return sve.replot(args.replot)
    return sve.run(args, overrides, sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
