"""The per-frame pieces every animated measurement uses (``scripts/bench_animation.py``, ``scripts/bench_debias.py``):
a frame's path-traced image, NRC's frames, a frame's reference (its own camera and lights:
:func:`nrc.scene.animated_scene`), the error of scored frames raw and denoised."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from lab.render import nrc_run, pt_render
from nrc.evaluation.reference import REF_SEED
from nrc.metrics import mean_ratio, rel_mse


def pt_image(cfg: Any, scene: Any, spp: int, seed: int) -> tuple[np.ndarray, float]:
    """A path-traced image (float64, non-finite values 0) and its wall time
    (:func:`lab.render.pt_render`)."""
    image, seconds = pt_render(scene, cfg, spp, seed)
    return image.astype(np.float64), seconds


def nrc_frames(cfg: Any, scene: Any, frames: int, seed: int, keep: Any = (),
               accumulate: bool = False) -> tuple[list[np.ndarray], list[float], np.ndarray, dict]:
    """Run NRC for ``frames`` frames (:func:`lab.render.nrc_run`); the frames in ``keep``
    (their images) and their times per frame, the final output (the accumulated image with ``accumulate``) and
    the metrics."""
    images, times = [], []

    def on_frame(frame: int, image: np.ndarray, output: np.ndarray, stats: dict) -> None:
        if frame in keep:
            images.append(np.asarray(image, np.float64))
            times.append(float(stats["time_frame_s"]))

    res = nrc_run(scene, cfg, int(scene.integrator.spp), seed, frames, accumulate, on_frame)
    return images, times, res.image.astype(np.float64), res.metrics


def frame_reference(cfg: Any, scene: Any, spp: int, chunk: int, path: Path) -> np.ndarray:
    """A path-traced reference of ``scene`` (one frame's camera and lights) with seeds from the reference stream,
    cached at ``path``."""
    from nrc.io import read_exr, write_exr

    if path.is_file():
        return read_exr(path)[0][..., :3].astype(np.float64)
    total = None
    for i in range(spp // chunk):
        img, _ = pt_image(cfg, scene, chunk, REF_SEED + 5000 + i)
        total = img if total is None else total + img
    ref = total / (spp // chunk)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(path, ref.astype(np.float32), {"spp": int(spp), "what": "animation frame reference"})
    return ref


def score(images: list[np.ndarray], refs: list[np.ndarray], masks: list[np.ndarray]) -> dict[str, Any]:
    """Mean relMSE and image mean over the medium pixels of ``images`` against ``refs``, raw and denoised by OIDN
    (``*_oidn``), the clamp bias, and the denoiser's median time per image (``oidn_s``)."""
    from nrc.denoise import clamp_bias, denoise

    den, times = [], []
    for x in images:
        t0 = time.perf_counter()
        den.append(denoise(x).astype(np.float64))
        times.append(time.perf_counter() - t0)
    out: dict[str, Any] = {"oidn_s": float(np.median(times))}
    for tag, ims in (("", images), ("_oidn", den)):
        out["rel_mse_medium" + tag] = float(np.mean([rel_mse(x, r, m) for x, r, m in zip(ims, refs, masks)]))
        out["mean_ratio_medium" + tag] = float(np.mean([mean_ratio(x, r, m) for x, r, m in zip(ims, refs, masks)]))
    out["clamp_bias"] = float(np.mean([clamp_bias(x) for x in images]))
    return out


