"""The README figure: the path tracer at a few spp, NRC after N frames, and a converged reference, side by side.

Usage::

    python scripts/figure_nrc_vs_pt.py [--frames 30] [--spp 4] [--ref-spp 1024] [--exposure 2] \\
        [--out docs/images/nrc_vs_pt.png] [hydra overrides ...]

Both renderers run on the same scene (the default: the procedural cloud under the sun, 160 x 90) with
``spp`` samples per pixel per frame; NRC runs ``frames`` frames from an untrained cache and the figure shows
its last frame. The reference is ``data/references/reference_<scene hash>_<ref-spp>spp.exr`` (rendered with
the compiled path tracer when missing, like ``scripts/render_reference.py``). Prints, and writes next to the
figure as JSON, each image's relative MSE and mean over the medium pixels against the reference's, and the
time per frame.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import open_dict

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from nrc.config import absolute_paths, compose  # noqa: E402
from nrc.io.png import tonemap  # noqa: E402
from nrc.evaluation.metrics import medium_mask, rel_mse  # noqa: E402
from nrc.render.radiance_caching import NRCRenderer  # noqa: E402
from nrc.render.pt import PathTracer  # noqa: E402
from nrc.evaluation.reference import read_reference, render_reference  # noqa: E402
from nrc.scene import load_scene  # noqa: E402
from nrc.evaluation.reference import REF_SEED, default_reference_path  # noqa: E402


def config(overrides: list[str]):
    cfg = compose(overrides)
    absolute_paths(cfg)
    return cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=30, help="NRC frames (the figure shows the last)")
    ap.add_argument("--spp", type=int, default=4, help="samples per pixel per frame, both renderers")
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--exposure", type=float, default=2.0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "images" / "nrc_vs_pt.png")
    args, overrides = ap.parse_known_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref_cfg = config(["renderer=pt", "renderer.backend=compiled", f"scene.integrator.spp={args.ref_spp}",
                      f"scene.integrator.seed={REF_SEED}", *overrides])
    ref_path = default_reference_path(ref_cfg, args.ref_spp)
    if not ref_path.is_file():
        render_reference(ref_cfg, ref_path, min(args.ref_spp, 256), args.ref_spp)
    ref = read_reference(ref_path)
    mask = medium_mask(ref.alpha) if ref.alpha is not None else None
    ref_mean = float(ref.image[mask].mean()) if mask is not None else float(ref.image.mean())

    pt_cfg = config(["renderer=pt", f"scene.integrator.spp={args.spp}", *overrides])
    pt = PathTracer(load_scene(pt_cfg.scene), pt_cfg)
    pt.render()  # first-use costs (and a compile, if the backend compiles) before the timed render
    t0 = time.perf_counter()
    pt_img = pt.render().image
    pt_time = time.perf_counter() - t0

    nrc_cfg = config(["renderer=nrc", f"scene.integrator.spp={args.spp}", "renderer.log.tensorboard=false",
                      *overrides])
    with open_dict(nrc_cfg):
        nrc_cfg.frames = args.frames
    frame_times: list[float] = []
    last: dict[str, np.ndarray] = {}

    def on_frame(frame: int, image: np.ndarray, accumulated: np.ndarray, stats: dict) -> None:
        frame_times.append(float(stats["time_frame_s"]))
        last["image"] = np.nan_to_num(np.asarray(image, np.float32))

    NRCRenderer(load_scene(nrc_cfg.scene), nrc_cfg).render(progress=True, on_frame=on_frame)
    nrc_img = last["image"]

    def score(img: np.ndarray) -> dict[str, float]:
        mean = float(img[mask].mean()) if mask is not None else float(img.mean())
        return {"rel_mse": rel_mse(img, ref.image), "rel_mse_medium": rel_mse(img, ref.image, mask),
                "mean_over_reference": mean / ref_mean}

    late = frame_times[len(frame_times) // 2:]
    result = {
        "overrides": overrides, "spp": args.spp, "frames": args.frames, "reference": str(ref_path.relative_to(REPO) if ref_path.is_relative_to(REPO) else ref_path),
        "reference_spp": args.ref_spp, "reference_rel_mse_floor": ref.rel_mse_floor,
        "pt": {**score(pt_img), "time_per_frame_s": pt_time},
        "nrc": {**score(nrc_img), "time_per_frame_s": float(np.mean(late))},
    }
    titles = [f"pt, {args.spp} spp: relMSE {result['pt']['rel_mse']:.3f}, {pt_time:.2f} s",
              f"nrc, frame {args.frames}: relMSE {result['nrc']['rel_mse']:.3f}, {np.mean(late):.2f} s",
              f"reference ({args.ref_spp} spp)"]
    h, w = ref.image.shape[:2]
    fig, axes = plt.subplots(1, 3, figsize=(3 * w / 40, h / 40 + 0.5), dpi=100)
    for ax, img, title in zip(axes, (pt_img, nrc_img, ref.image), titles):
        ax.imshow(tonemap(img, args.exposure))
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    args.out.with_suffix(".json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
