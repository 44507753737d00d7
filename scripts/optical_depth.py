"""Median optical depth over the camera rays that see the medium, for scene presets (docs/scenes.md's table).

    python scripts/optical_depth.py                      # every conf/scene preset and every speed-vs-error type
    python scripts/optical_depth.py --type thick_disney  # one speed-vs-error scene type
    python scripts/optical_depth.py scene=sun scene.volume.density_scale=2   # any Hydra overrides

Prints a Markdown table: median, 10th and 90th percentile of tau over the pixels whose centre ray meets the
medium, the median of tau (1 - g), albedo, g and the share of the pixels that see the medium
(nrc/volume/optical_depth.py). Run from the repository root (the Disney cloud is ../shared/data/...).
"""

from __future__ import annotations

import argparse
import sys

from lab import exit_status
from lab.render import setup
from nrc.config import PRESETS, preset
from nrc.volume.optical_depth import scene_optical_depth


def row(name: str, overrides: list[str]) -> str:
    run = setup(overrides, absolute=True)
    cfg, scene = run.cfg, run.scene
    od = scene_optical_depth(scene)
    v = cfg.scene.volume
    src = "Disney" if v.source == "vdb" else v.procedural.kind if v.source == "procedural" else v.source
    return (f"| `{name}` | {src} | {float(v.density_scale):g} | {od.median:.1f} | {od.p10:.1f}-{od.p90:.1f} | "
            f"{od.median_reduced:.1f} | {scene.albedo:g} | {scene.g:g} | {100 * od.medium_pixels / od.pixels:.0f} % |")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--type", action="append", default=[], choices=PRESETS, help="scene type (conf/scene/)")
    args, overrides = p.parse_known_args(argv)
    if overrides:
        jobs = [(" ".join(overrides), overrides)]
    elif args.type:
        jobs = [(f"scene={t}", preset(t)) for t in args.type]
    else:
        jobs = [(f"scene={t}", preset(t)) for t in PRESETS if t != "none"]
    print("| scene | cloud | density scale | median tau | tau p10-p90 | median tau(1-g) | albedo | g | pixels seeing it |")
    print("|---|---|---|---|---|---|---|---|---|")

    def rows() -> None:
        for name, ovs in jobs:
            print(row(name, ovs), flush=True)

    return exit_status("optical_depth", rows)


if __name__ == "__main__":
    sys.exit(main())
