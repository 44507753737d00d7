"""Reports of the thesis experiments and the speed-versus-error runs; the report code lives in
:mod:`nrc.evaluation.experiments`, this is its command line.

    python scripts/experiments_report.py [encodings extra_inputs batch_filters transmittance nrc_vs_pt] [--results]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nrc.evaluation import experiments as ex


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("reports", nargs="*", default=list(ex.REPORTS), help=f"any of {', '.join(ex.REPORTS)}")
    p.add_argument("--root", type=Path, default=ex.REPO / "multirun" / "experiments")
    p.add_argument("--docs", type=Path, default=ex.REPO / "docs")
    p.add_argument("--results", action="store_true",
                   help="also assemble docs/results.md and rewrite the README's generated figure captions")
    p.add_argument("--readme", type=Path, default=None,
                   help="the README whose generated blocks --results rewrites (default: README.md beside --docs)")
    p.add_argument("--intro", type=Path, default=ex.REPO / "docs" / "results_intro.md",
                   help="hand-written Markdown placed at the top of results.md (if it exists)")
    p.add_argument("--conditions", default=ex.CONDITIONS["text"],
                   help="how the multiruns were run (threads, other jobs), stated with each report")
    return p


def main(argv: list[str] | None = None) -> int:
    return ex.run_reports(parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
