"""Russian roulette on long paths: cost and noise of the path tracer's survival rules on one scene.

    python scripts/bench_roulette.py --reference data/references/thick_64x36.exr scene=thick \\
        scene.camera.width=64 scene.camera.height=36 [--spp 64] [--seeds 3]

Variants (``renderer.russian_roulette``): off; the throughput rule from vertex 8 (``max_survival`` 1: q = max
throughput, weights never above 1; at albedo 1 it never fires); and Mitsuba 3's cap (``max_survival`` 0.95, or
``--caps``), whose weights grow as 0.95^-n. Each renders ``--seeds`` independent images with the compiled path
tracer; prints, per variant, the render time, scattering events per sample, relMSE over the medium pixels (minus
the reference's floor), the image mean over the reference's, the relative per-pixel variance across the seeds,
and relMSE x time (the efficiency: lower is better) as a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lab.render import setup
from nrc.metrics import mean_ratio, medium_mask, rel_mse, relative_variance
from nrc.evaluation.reference import read_reference
from nrc.volume.optical_depth import camera_optical_depths


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--reference", type=Path, default=None,
                   help="converged reference EXR (default: the mean of the 'off' renders, a noisy stand-in)")
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--start", type=int, default=8)
    p.add_argument("--caps", default="0.95", help="comma-separated max_survival values below 1 to try")
    p.add_argument("--out", type=Path, default=None)
    args, overrides = p.parse_known_args(argv)
    ref = read_reference(args.reference) if args.reference else None
    mask = medium_mask(ref.alpha) if ref else None
    floor = ref.attrs.get("rel_mse_floor_medium") if ref else None
    rr = "renderer.russian_roulette"
    variants = {"off": [f"{rr}.enabled=false"],
                "throughput": [f"{rr}.enabled=true", f"{rr}.start={args.start}", f"{rr}.max_survival=1.0"]}
    for cap in [c for c in args.caps.split(",") if c]:
        variants[f"cap {cap}"] = [f"{rr}.enabled=true", f"{rr}.start={args.start}", f"{rr}.max_survival={cap}"]
    rows, renders = [], {}
    for name, ovs in variants.items():
        imgs, times, scat = [], [], []
        for seed in range(args.seeds):
            run = setup(["renderer=pt", "renderer.backend=compiled", *overrides, *ovs,
                         f"scene.integrator.spp={args.spp}", f"scene.integrator.seed={100 + seed}"], absolute=True)
            r = run.renderer().render()
            imgs.append(r.image.astype(np.float64))
            times.append(r.metrics["time_render_s"])
            scat.append(r.metrics["scatter_events"] / r.metrics["samples"])
        if ref is None:  # the 'off' renders' mean stands in for the reference (runs first)
            ref = type("Ref", (), {"image": np.mean(imgs, axis=0)})()
            scene = run.scene
            mask = (camera_optical_depths(scene.camera, scene.grid) > 0).reshape(
                scene.camera.height, scene.camera.width).numpy()
        renders[name] = imgs
        e = float(np.mean([rel_mse(x, ref.image, mask) for x in imgs]))
        t = float(np.median(times))
        rows.append({"variant": name, "time_render_s": t, "scatter_per_sample": float(np.mean(scat)),
                     "rel_mse_medium": e, "rel_mse_medium_corr": e - floor if floor is not None else e,
                     "mean_ratio_medium": float(np.mean([mean_ratio(x, ref.image, mask) for x in imgs])),
                     "variance_medium": relative_variance(np.stack(imgs), ref.image, mask),
                     "max_pixel": float(max(x.max() for x in imgs))})
        rows[-1]["efficiency"] = rows[-1]["rel_mse_medium_corr"] * t
        print(json.dumps(rows[-1]), flush=True)
    print(f"\n{args.spp} spp, {args.seeds} seeds; reference: " + (f"floor (medium) {floor:.3g}\n" if floor is not None
          else "the mean of the 'off' renders (their own relMSE includes their noise twice over)\n"))
    print("| roulette | render (s) | events / sample | relMSE medium (floor-corr.) | mean / ref | rel. variance | "
          "relMSE x time | brightest pixel |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['variant']} | {r['time_render_s']:.2f} | {r['scatter_per_sample']:.1f} | "
              f"{r['rel_mse_medium_corr']:.4g} | {r['mean_ratio_medium']:.4f} | {r['variance_medium']:.4g} | "
              f"{r['efficiency']:.4g} | {r['max_pixel']:.3g} |")
    if args.out is not None:
        args.out.write_text(json.dumps({"argv": sys.argv[1:], "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
