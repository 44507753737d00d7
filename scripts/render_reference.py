"""Render a converged ``pt`` reference: a thin wrapper over the reference app (``python -m nrc.reference_app``,
:func:`nrc.reference_app.ensure_reference`), kept for its short command line.

Hydra overrides select the scene as for ``python -m nrc``; ``scene.integrator.spp`` is the total sample count and
``scene.integrator.seed`` the base seed (moved into the reference stream, disjoint from every render's seeds). A
killed run resumes from its part beside the EXR (``<out>.parts/``) when started again with the same arguments.

Usage::

    python scripts/render_reference.py scene=sun scene.integrator.spp=4096 --chunk-spp 64 \\
        [--out data/references/sun.exr] [--no-progress]

Without ``--out`` the reference goes to ``data/references/reference_<scene hash prefix>_<spp>spp.exr`` under
``$NRC_REFERENCE_DIR`` or the working directory (the name ``scripts/speed_vs_error.py`` looks for). Several
processes or cluster nodes: ``python -m nrc.reference_app -m ... reference.chunks=...`` (docs/running.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lab import exit_status
from nrc.config import compose
from nrc.reference_app import ensure_reference


def main(argv: list[str] | None = None) -> int:
    """Parse ``--chunk-spp/--out/--no-progress`` and Hydra overrides, render; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--chunk-spp", type=int, default=64, help="samples per pixel per chunk (default 64)")
    parser.add_argument("--out", type=Path, default=None, help="output EXR (default data/references/...)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args, overrides = parser.parse_known_args(argv)
    return exit_status("render_reference", lambda: ensure_reference(
        overrides, int(compose(overrides).scene.integrator.spp), args.chunk_spp, args.out,
        progress=not args.no_progress))


if __name__ == "__main__":
    sys.exit(main())
