"""NRC's error over frames, raw and denoised by OIDN, for a few configurations of one scene type.

Usage::

    python scripts/nrc_convergence.py --preset side_lit --reference data/references/<ref>.exr --frames 150 \
        --variant a=renderer.training.width=64,renderer.training.height=64 --variant b= [--out conv.json] [scene overrides]

Every variant runs the NRC renderer (compiled, seed 1001, the renderer's and scene's defaults -- 4 spp per
frame unless ``scene.integrator.spp`` is given -- plus the variant's Hydra overrides) for ``--frames`` frames from an untrained cache; at frames 10, 20, 30, 50, 75, 100, 150, 200 and 300
it prints and records the frame's relMSE over the medium pixels, raw and denoised (pyoidn), its image mean over
the reference's (medium pixels), and the wall time since the renderer started (start-up and compilation
included). The reference must come from the disjoint seed stream (``scripts/render_reference.py``).
docs/measurements/nrc_defaults.md ("Defaults by measurement", "Thick clouds" and "Training budget on small images") shows
what it measured.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lab.render import setup, stopped_by
from nrc.denoise import denoise  # noqa: E402
from nrc.metrics import mean_ratio, medium_mask, rel_mse  # noqa: E402
from nrc.evaluation.reference import check_independent, read_reference  # noqa: E402
from nrc.config import PRESETS, preset  # noqa: E402

MARKS = (10, 20, 30, 50, 75, 100, 150, 200, 300)
SEED = 1001


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--preset", choices=PRESETS, required=True)
    p.add_argument("--reference", type=Path, required=True)
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--variant", action="append", default=[], metavar="NAME=OV1,OV2", required=True)
    p.add_argument("--out", type=Path, default=None, help="JSON of the recorded points")
    args, scene = p.parse_known_args(argv)
    ref = read_reference(args.reference)
    if ref.alpha is None:
        raise SystemExit(f"nrc_convergence: {args.reference} has no alpha (A channel); re-render it")
    check_independent(ref.attrs, range(SEED, SEED + 1), args.reference)
    mask = medium_mask(ref.alpha)
    out: dict[str, list[dict]] = {}
    for spec in args.variant:
        name, _, ovs = spec.partition("=")
        t0 = time.perf_counter()  # the scene's load, the renderer's start-up and its frames
        run = setup(preset(args.preset) + scene + ["renderer=nrc", "renderer.log.tensorboard=false",
                                                    "renderer.backend=compiled", f"frames={args.frames}",
                                                    f"scene.integrator.seed={SEED}"]
                    + [o for o in ovs.split(",") if o])
        cfg = run.cfg
        if ref.image.shape != (cfg.scene.camera.height, cfg.scene.camera.width, 3):
            raise SystemExit(f"nrc_convergence: the reference is {ref.image.shape[:2]}, the scene "
                             f"{cfg.scene.camera.height}x{cfg.scene.camera.width}")
        rows: list[dict] = []

        def on_frame(frame, image, accumulated, stats, rows=rows, t0=t0, name=name):
            if frame + 1 not in MARKS:
                return
            img = np.nan_to_num(np.asarray(image, np.float64))
            rows.append({"frame": frame + 1, "time_s": time.perf_counter() - t0,
                         "time_frame_s": float(stats["time_frame_s"]),
                         "rel_mse_medium": rel_mse(img, ref.image, mask),
                         "rel_mse_medium_oidn": rel_mse(denoise(img).astype(np.float64), ref.image, mask),
                         "mean_ratio_medium": mean_ratio(img, ref.image, mask)})
            print(name, json.dumps(rows[-1]), flush=True)

        stopped_by(run.renderer().render(progress=False, on_frame=on_frame).metrics, run.cfg.frames)
        out[name] = rows
    if args.out is not None:
        args.out.write_text(json.dumps({"preset": args.preset, "scene": scene, "variants": args.variant,
                                        "points": out}, indent=2))
    return out


if __name__ == "__main__":
    main()
