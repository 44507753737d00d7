"""Animations measured end to end: NRC against the path tracer over a whole frame sequence.

The per-frame pieces every animated measurement uses (a frame's path-traced image, NRC's frames, a frame's
reference, the error of scored frames raw and denoised) and :func:`animation`: a ``frames``-long animation
(``renderer.animate.mode``: ``sun`` turns the directional lights, ``orbit`` the camera;
:func:`nrc.scene.animated_scene`) rendered from a cold start by each NRC configuration and by the path tracer at
several spp per frame, every ``score_every``-th frame scored against its own reference. The comparison is of
**whole runs**: each side's wall time for all ``frames`` frames -- the path tracer's first-use cost (loading or
compiling its step) and NRC's (its step, its untrained first frames) included, the denoiser's time per frame
added to both for the denoised rows -- and the mean error over the scored frames; the path tracer's error at
NRC's whole-run time is read off its measured points (:func:`nrc.evaluation.speed_vs_error.baseline_error`,
``extrapolated`` set when NRC's time lies outside them). Process start-up (importing torch, composing the
config) is the same for both and not counted. Run by ``scripts/bench_animation.py``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from nrc.config import compose
from nrc.evaluation.reference import REF_SEED, medium_alpha, scene_hash
from nrc.evaluation.speed_vs_error import baseline_error, nrc_run, pt_render, pt_warmup
from nrc.metrics import mean_ratio, medium_mask, rel_mse
from nrc.scene import animated_scene, load_scene

SEED_BASE = 1000  # render seeds; references use the disjoint stream from REF_SEED


def pt_image(cfg: Any, scene: Any, spp: int, seed: int) -> tuple[np.ndarray, float]:
    """A path-traced image (float64, non-finite values 0) and its wall time
    (:func:`~nrc.evaluation.speed_vs_error.pt_render`)."""
    image, seconds = pt_render(scene, cfg, spp, seed)
    return image.astype(np.float64), seconds


def nrc_frames(cfg: Any, scene: Any, frames: int, seed: int, keep: Any = (),
               accumulate: bool = False) -> tuple[list[np.ndarray], list[float], np.ndarray, dict]:
    """Run NRC for ``frames`` frames (:func:`~nrc.evaluation.speed_vs_error.nrc_run`); the frames in ``keep``
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


def animation(preset: list[str], configs: dict[str, list[str]], pt_spp: list[int], frames: int, score_every: int,
              mode: str, ref_spp: int, ref_chunk: int, ref_dir: Path, log: Any = print) -> dict[str, Any]:
    """The whole-run comparison (module docstring); rows per configuration with ``whole_s`` (wall time of all
    frames), ``whole_oidn_s`` (plus the denoiser on every frame) and the scores of the scored frames."""
    anim = [f"renderer.animate.mode={mode}"]
    pcfg = compose(["renderer=pt", "renderer.backend=compiled", *preset])  # the preset may choose another backend
    deg = float(compose(["renderer=nrc", *preset, *anim]).renderer.animate.degrees_per_frame)
    pscene = load_scene(pcfg.scene, pcfg.device)
    scenes = [animated_scene(pscene, mode, deg, f) for f in range(frames)]
    scored = list(range(score_every - 1, frames, score_every))
    h = scene_hash(pcfg)[:12]
    refs, masks = [], []
    for f in scored:
        t0 = time.perf_counter()
        refs.append(frame_reference(pcfg, scenes[f], ref_spp, ref_chunk,
                                    ref_dir / f"anim_{h}_{mode}{deg:g}_f{f}_{ref_spp}spp.exr"))
        masks.append(medium_mask(medium_alpha(scenes[f])))
        log(f"reference of frame {f}: {time.perf_counter() - t0:.1f} s")
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    pt_warmup(pscene, pcfg)  # the step's first use (loading its package or compiling): part of the whole run
    first_use = time.perf_counter() - t0
    for spp in pt_spp:
        ims, ts = [], []
        for f, s in enumerate(scenes):
            img, dt = pt_image(pcfg, s, spp, SEED_BASE + 97 * spp + f)
            ts.append(dt)
            if f in scored:
                ims.append(img)
        rows.append({"config": "pt", "spp": spp, "whole_s": first_use + float(np.sum(ts)),
                     "frame_s": float(np.median(ts)), "first_use_s": first_use, **score(ims, refs, masks)})
        log(rows[-1])
    for name, overrides in configs.items():
        cfg = compose(["renderer=nrc", *preset, *anim, *overrides, "renderer.log.tensorboard=false",
                       "renderer.checkpoint_every=0"])
        t0 = time.perf_counter()
        ims, ts, _, _ = nrc_frames(cfg, load_scene(cfg.scene, cfg.device), frames, SEED_BASE, keep=scored)
        whole = time.perf_counter() - t0
        rows.append({"config": name, "spp": int(cfg.scene.integrator.spp), "whole_s": whole,
                     "frame_s": float(np.median(ts)), **score(ims, refs, masks)})
        log(rows[-1])
    for r in rows:
        r["whole_oidn_s"] = r["whole_s"] + frames * r["oidn_s"]
    for tag, clock in (("", "whole_s"), ("_oidn", "whole_oidn_s")):
        points = [(r[clock], r["rel_mse_medium" + tag]) for r in rows if r["config"] == "pt"]
        lo, hi = min(p[0] for p in points), max(p[0] for p in points)
        for r in rows:
            if r["config"] != "pt":
                r["pt_rel_mse_medium" + tag] = baseline_error(points, r[clock])
                r["ratio_vs_pt" + tag] = r["rel_mse_medium" + tag] / r["pt_rel_mse_medium" + tag]
                r["extrapolated" + tag] = not lo <= r[clock] <= hi
    return {"rows": rows, "frames": frames, "scored_frames": scored, "mode": mode, "degrees_per_frame": deg,
            "ref_spp": ref_spp}


def markdown(result: dict[str, Any]) -> str:
    """The result as a Markdown table."""
    lines = ["| config | spp/frame | whole run (s) | + OIDN (s) | s/frame | relMSE medium | mean/ref | relMSE + OIDN | "
             "mean/ref + OIDN | pt at that whole time | pt + OIDN at that whole time |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        def vs(tag: str) -> str:
            if r["config"] == "pt":
                return "–"
            flag = " (extrapolated)" if r["extrapolated" + tag] else ""
            return f"{r['pt_rel_mse_medium' + tag]:.4g} (**{r['ratio_vs_pt' + tag]:.2f}x**){flag}"
        lines.append(f"| {r['config']} | {r['spp']} | {r['whole_s']:.1f} | {r['whole_oidn_s']:.1f} | "
                     f"{r['frame_s']:.3f} | {r['rel_mse_medium']:.4g} | {r['mean_ratio_medium']:.3f} | "
                     f"{r['rel_mse_medium_oidn']:.4g} | {r['mean_ratio_medium_oidn']:.3f} | {vs('')} | {vs('_oidn')} |")
    return "\n".join(lines) + "\n"
