"""Regenerate the README figures (docs/images/clouds.png, nrc_vs_pt.png/.json, sun.webp, figures.json).

Usage::

    python scripts/make_figures.py [--out docs/images] [--hero-spp 512] [--frames 30] [--anim-frames 36] ...

About 15 minutes on 2 cores with the defaults (the converged references are cached in data/references/ and
resume after an interruption). See nrc/evaluation/figures.py for what each figure shows.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from nrc.evaluation import figures as fig


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=fig.REPO / "docs" / "images")
    ap.add_argument("--hero-width", type=int, default=256)
    ap.add_argument("--hero-height", type=int, default=144)
    ap.add_argument("--hero-spp", type=int, default=1536)
    ap.add_argument("--width", type=int, default=160, help="comparison and animation width")
    ap.add_argument("--height", type=int, default=90)
    ap.add_argument("--spp", type=int, default=4, help="NRC spp per frame")
    ap.add_argument("--frames", type=int, default=30, help="NRC frames before the comparison")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--chunk-spp", type=int, default=64)
    ap.add_argument("--ref-dir", type=Path, default=fig.REPO / "data" / "references", help="cache of the references")
    ap.add_argument("--comparison", choices=sorted(fig.COMPARISONS), default="side_lit",
                    help="scene of the equal-time comparison")
    ap.add_argument("--anim-spp", type=int, default=6,
                    help="path tracer spp of the animation when the comparison is not the default scene")
    ap.add_argument("--anim-frames", type=int, default=36, help="recorded frames (one full turn of the sun)")
    ap.add_argument("--anim-warmup", type=int, default=10, help="NRC frames trained before recording")
    ap.add_argument("--backend", default="compiled", help="pt backend of the references (and NRC)")
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: heroes,comparison,animation")
    return ap


def main(argv: list[str] | None = None) -> dict[str, Any]:
    return fig.make_figures(parser().parse_args(argv))


if __name__ == "__main__":
    main()
