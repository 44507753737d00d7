"""Render a converged ``pt`` reference in resumable chunks (see :mod:`nrc.render.reference`).

Hydra overrides select the scene as for ``python -m nrc``; ``scene.integrator.spp`` is the total sample
count and ``scene.integrator.seed`` the base seed (chunk ``i`` uses ``seed + i``). A killed run resumes
from ``<out>.ckpt.npz`` when started again with the same arguments.

Usage::

    python scripts/render_reference.py scene=sun scene.integrator.spp=4096 --chunk-spp 64 \\
        [--out data/references/sun.exr] [--no-progress]

Without ``--out`` the reference goes to ``data/references/reference_<config hash prefix>.exr``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from nrc.app import CONF_DIR, _absolute_paths  # noqa: E402
from nrc.errors import NRCError  # noqa: E402
from nrc.render.reference import config_hash, render_reference  # noqa: E402

DEFAULT_DIR = REPO / "data" / "references"


def main(argv: list[str] | None = None) -> int:
    """Parse ``--chunk-spp/--out/--no-progress`` and Hydra overrides, render; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--chunk-spp", type=int, default=64, help="samples per pixel per chunk (default 64)")
    parser.add_argument("--out", type=Path, default=None, help="output EXR (default data/references/...)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args, overrides = parser.parse_known_args(argv)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    try:
        _absolute_paths(cfg)
        out = args.out or DEFAULT_DIR / f"reference_{config_hash(cfg)[:12]}.exr"
        render_reference(cfg, out, args.chunk_spp, int(cfg.scene.integrator.spp), progress=not args.no_progress)
    except NRCError as exc:
        print(f"render_reference: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
