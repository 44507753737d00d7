"""Render a converged ``pt`` reference in resumable chunks (see :mod:`nrc.evaluation.reference`).

Hydra overrides select the scene as for ``python -m nrc``; ``scene.integrator.spp`` is the total sample
count and ``scene.integrator.seed`` the base seed, moved into the reference seed stream (>= 1e6, disjoint from
every render's seeds: chunk ``i`` of seed ``s`` uses ``1e6 + s * 1e4 + i``). A killed run resumes
from ``<out>.ckpt.npz`` when started again with the same arguments.

Usage::

    python scripts/render_reference.py scene=sun scene.integrator.spp=4096 --chunk-spp 64 \\
        [--out data/references/sun.exr] [--no-progress]

Without ``--out`` the reference goes to ``data/references/reference_<scene hash prefix>_<spp>spp.exr``
(the name ``scripts/speed_vs_error.py`` looks for). The EXR's ``A`` channel is the medium alpha
(``1 -`` camera-ray transmittance) and its header holds ``spp``, ``seed``, ``config_hash``, ``scene_hash``
and ``rel_mse_floor`` (the relative MSE the reference's own noise adds to any comparison with it).
A tqdm bar over chunks shows the elapsed time and the ETA.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


REPO = Path(__file__).resolve().parent.parent

from nrc.config import absolute_paths, compose  # noqa: E402
from nrc.errors import NRCError  # noqa: E402
from nrc.evaluation.reference import default_reference_path, read_reference, render_reference  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Parse ``--chunk-spp/--out/--no-progress`` and Hydra overrides, render; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--chunk-spp", type=int, default=64, help="samples per pixel per chunk (default 64)")
    parser.add_argument("--out", type=Path, default=None, help="output EXR (default data/references/...)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args, overrides = parser.parse_known_args(argv)
    cfg = compose(overrides)
    try:
        absolute_paths(cfg)
        out = args.out or default_reference_path(cfg, int(cfg.scene.integrator.spp))
        render_reference(cfg, out, args.chunk_spp, int(cfg.scene.integrator.spp), progress=not args.no_progress)
    except NRCError as exc:
        print(f"render_reference: error: {exc}", file=sys.stderr)
        return 2
    ref = read_reference(out)
    print(f"wrote {out} (rel_mse_floor: all {ref.attrs['rel_mse_floor']:.3g}, "
          f"medium {ref.attrs['rel_mse_floor_medium']:.3g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
