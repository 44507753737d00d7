"""How much light a path-length limit cuts off: the path tracer at several ``scene.integrator.max_scatter``.

    python scripts/max_scatter.py scene=thick scene.camera.width=64 scene.camera.height=36 \\
        scene.integrator.spp=64 --limits 256,1024,4096

Every limit renders the same paths (same seed: a path's random numbers depend on (seed, sample id, step) only,
so two limits differ only by what the shorter one cuts off) with the compiled path tracer. Prints, per limit,
the image mean over the pixels that see the medium relative to the largest limit's (the light cut off), the
99th percentile and the largest per-pixel shortfall (pixel means over 3x3 blocks, relative to the largest
limit's), the render time, scattering events per sample and tracking steps; and writes them as JSON with
``--out``. docs/scenes.md ("Thick clouds") shows what it measured.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from lab.render import setup
from nrc.volume.optical_depth import camera_optical_depths


def _blocks(img: np.ndarray, k: int = 3) -> np.ndarray:
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k, 3).mean(axis=(1, 3))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--limits", default="256,1024,4096", help="comma-separated max_scatter values")
    p.add_argument("--out", type=Path, default=None)
    args, overrides = p.parse_known_args(argv)
    limits = sorted(int(x) for x in args.limits.split(","))
    rows, images = [], {}
    mask = None
    for limit in limits:
        run = setup(["renderer=pt", "renderer.backend=compiled", *overrides, f"scene.integrator.max_scatter={limit}"],
                    absolute=True)
        scene = run.scene
        if mask is None:
            tau = camera_optical_depths(scene.camera, scene.grid).reshape(scene.camera.height, scene.camera.width)
            mask = tau.numpy() > 0
        t0 = time.perf_counter()
        r = run.renderer().render()
        images[limit] = r.image.astype(np.float64)
        rows.append({"max_scatter": limit, "time_render_s": r.metrics["time_render_s"],
                     "time_total_s": time.perf_counter() - t0,
                     "scatter_per_sample": r.metrics["scatter_events"] / r.metrics["samples"],
                     "tracking_steps": r.metrics["tracking_steps"], "iterations": r.metrics["iterations"]})
    top = images[limits[-1]]
    top_b = _blocks(top)
    for row in rows:
        img = images[row["max_scatter"]]
        row["mean_ratio_medium"] = float(img[mask].mean() / top[mask].mean())
        short = 1.0 - _blocks(img).mean(-1) / np.maximum(top_b.mean(-1), 1e-12)
        seen = _blocks(np.repeat(mask[..., None], 3, -1).astype(np.float64))[..., 0] > 0.5
        row["shortfall_p99"] = float(np.percentile(short[seen], 99))
        row["shortfall_max"] = float(short[seen].max())
        print(json.dumps(row), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps({"overrides": overrides, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
