"""Reservoir reuse (``renderer.reuse.mode``) against none: 1-spp frames of the path tracer, raw and denoised.

For each scene type, ``--frames`` 1-spp frames of a static camera are rendered per mode in one process:
``none`` as independent 1-spp renders (seeds), ``spatial`` and ``spatiotemporal`` as the passes of one
``spp = frames`` render (``PathTracer.render(on_pass=...)``; temporal reuse chains the passes). Each frame is
scored against a converged reference (``--ref-spp``, rendered once with ``none`` and kept in ``--out``):
relMSE (medium pixels), the image mean over the reference's (bias), HDR-FLIP, and the same after Intel Open
Image Denoise (``pyoidn``). Frames before ``--warmup`` are left out of the means (temporal reuse needs a few
frames of history). Seconds per frame: the median over frames (with reuse, each pass's trace + reuse pass;
``none``: the render call). Equal time: the ``none`` relMSE at a reuse frame's time is its 1-spp relMSE scaled
by ``t_none / t_reuse`` (raw: relMSE of an unbiased estimator falls as 1 / samples), and ``none`` is also
rendered at ``ceil(t_reuse / t_none)`` spp for the denoised comparison at equal time (OIDN does not scale so).

    python scripts/bench_reuse.py [--scenes many_lights,side_lit] [--frames 12] [--warmup 4]
        [--out outputs/bench_reuse] [--extra renderer.reuse.neighbors=4 ...] [--nrc many_lights]

``--nrc`` scene types also run ``renderer=nrc`` frames of the static camera (``none`` against
``spatiotemporal``; the reference must exist, i.e. the scene was in ``--scenes`` once).

``--decompose`` scene types (``name`` or ``name:override,override``) get the variance decomposition instead:
each 1-spp pass is split into ``A`` (everything but the reuse vertex's direct light: what the trace adds) and
that direct light estimated by the vertex's own RIS (``B``, the ``none`` estimator) and by each reuse variant
(``C``: spatial / spatiotemporal x ``mis`` balance / pairwise, each with its own history, all on the same
vertices). Per-pixel variances over the passes (the first ``--warmup`` left out), relative to the mean image
squared + 0.01 and averaged over the medium's pixels as relMSE is, give: the direct light's share of the pixel,
the frame's relative variance with ``B`` and with each ``C``, and the ceiling ``var(A + B) / var(A)``, the gain
per frame of a noiseless direct-light estimate at the vertex, which no reuse of light samples there can beat.
``--decompose-nrc`` scene types do the same for 1-spp NRC frames of a static camera (:func:`decompose_nrc`),
where the cache replaces the rest of the path: both estimators' frames on one cache, against the reference.
``--oracle-nrc`` scene types (``name`` or ``name:override,override``; ``';'`` between them) bound what any reuse
of the distance domain could give (:func:`oracle_nrc`): the frames with the camera ray's single scattering
replaced by its expectation, at no cost, raw and after OIDN, beside ``none`` and the real estimators; with
``renderer.debias.probability=1`` in the overrides the frames are the path tracer's estimator.

Writes ``bench.json`` and ``bench.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import torch

from lab import REPO
from lab.machine import machine
from lab.render import renderer, setup

from nrc.config import code_version  # noqa: E402
from nrc.metrics import hdr_flip, medium_mask, rel_mse  # noqa: E402
from nrc.render.preview import medium_alpha  # noqa: E402
from nrc.config import preset  # noqa: E402

MODES = ("none", "spatial", "spatiotemporal")
COMMON = ["renderer=pt", "renderer.backend=eager", "renderer.light_selection=ris"]


def render(overrides: list[str], on_pass=None):
    run = setup(overrides)
    t0 = time.perf_counter()
    res = run.renderer().render(on_pass=on_pass)
    return res, time.perf_counter() - t0, run.scene


def medium(overrides: list[str]) -> np.ndarray:
    """The medium pixels (:func:`nrc.metrics.medium_mask`) of the scene ``overrides`` configure."""
    return medium_mask(medium_alpha(setup(overrides).scene))


def score(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    from nrc.denoise import denoise

    den = denoise(img)
    return {"rel_mse": rel_mse(img, ref, mask), "mean_ratio": float(img.mean() / ref.mean()),
            "flip": hdr_flip(img, ref), "rel_mse_oidn": rel_mse(den, ref, mask),
            "mean_ratio_oidn": float(den.mean() / ref.mean()), "flip_oidn": hdr_flip(den, ref)}


def mean_score(frames, ref: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """:func:`score` averaged over ``frames`` (each ``(H, W, 3)``)."""
    scores = [score(f, ref, mask) for f in frames]
    return {k: float(np.mean([s[k] for s in scores])) for k in scores[0]}


def parse_spec(spec: str) -> tuple[str, list[str]]:
    """A scene type ``name`` or ``name:override,override`` as ``(name, overrides)``."""
    name, _, more = spec.partition(":")
    return name, [o for o in more.split(",") if o]


def nrc_overrides(name: str, args, extra=(), defaults=()) -> list[str]:
    """1-spp NRC frames of the scene type's static camera (eager, RIS light selection, no TensorBoard,
    ``--nrc-frames`` frames): ``defaults`` (which ``--extra`` may override), then ``--extra``, then ``extra``."""
    return [*preset(name), "renderer=nrc", "renderer.backend=eager", "renderer.light_selection=ris",
            "renderer.log.tensorboard=false", f"frames={args.nrc_frames}", "scene.integrator.spp=1", *defaults,
            *args.extra, *extra]


def bench_scene(name: str, args, log) -> dict:
    base = [*preset(name), *COMMON, *args.extra]
    ref = reference(name, base, args, log)
    mask = medium(base)
    out: dict = {"scene": name, "overrides": base, "modes": {}}
    for mode in MODES:
        frames, times = [], []
        if mode == "none":
            for f in range(args.frames):
                res, secs, _ = render([*base, "scene.integrator.spp=1", f"scene.integrator.seed={f + 1}"])
                frames.append(res.image)
                times.append(res.metrics["time_render_s"])
        else:
            stamps = [time.perf_counter()]

            def on_pass(j, img):
                frames.append(img.cpu().numpy().copy())
                stamps.append(time.perf_counter())

            res, secs, _ = render([*base, f"renderer.reuse.mode={mode}", f"scene.integrator.spp={args.frames}",
                                   "scene.integrator.seed=1"], on_pass)
            times = list(np.diff(stamps))
            out.setdefault("reuse_metrics", {})[mode] = {k: v for k, v in res.metrics.items() if k.startswith("reuse")}
        row = mean_score(frames[args.warmup:], ref, mask)
        row["seconds_per_frame"] = float(np.median(times[args.warmup:] if mode != "none" else times))
        out["modes"][mode] = row
        log(f"{name} {mode}: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()))
    t_none = out["modes"]["none"]["seconds_per_frame"]
    for mode in MODES[1:]:
        row = out["modes"][mode]
        k = max(1, math.ceil(row["seconds_per_frame"] / t_none - 0.05))
        eq = []
        for f in range(args.equal_time_frames):
            res, _, _ = render([*base, f"scene.integrator.spp={k}", f"scene.integrator.seed={1000 + f}"])
            eq.append(score(res.image, ref, mask))
        row["equal_time_spp_none"] = k
        row["none_rel_mse_at_equal_time"] = out["modes"]["none"]["rel_mse"] * t_none / row["seconds_per_frame"]
        row["none_rel_mse_oidn_at_equal_time"] = float(np.mean([s["rel_mse_oidn"] for s in eq]))
        row["gain_raw_equal_time"] = row["none_rel_mse_at_equal_time"] / row["rel_mse"]
        row["gain_oidn_equal_time"] = row["none_rel_mse_oidn_at_equal_time"] / row["rel_mse_oidn"]
        log(f"{name} {mode}: equal-time gain raw {row['gain_raw_equal_time']:.2f}x, "
            f"OIDN {row['gain_oidn_equal_time']:.2f}x (none at {k} spp)")
    return out


NRC_VARIANTS = {"none": ["renderer.reuse.mode=none"],
                "spatiotemporal": ["renderer.reuse.mode=spatiotemporal"],
                "distance_own": ["renderer.reuse.mode=spatial", "renderer.reuse.neighbors=0",
                                 "renderer.reuse.domain=distance", "renderer.reuse.target=coarse"],
                "distance_spatial": ["renderer.reuse.mode=spatial", "renderer.reuse.domain=distance",
                                     "renderer.reuse.target=coarse"],
                "distance_spatiotemporal": ["renderer.reuse.mode=spatiotemporal", "renderer.reuse.domain=distance",
                                            "renderer.reuse.target=coarse"],
                "distance_own_fine": ["renderer.reuse.mode=spatial", "renderer.reuse.neighbors=0",
                                      "renderer.reuse.domain=distance", "renderer.reuse.target=fine",
                                      "renderer.reuse.distance_steps=256"],
                "distance_temporal_fine": ["renderer.reuse.mode=spatiotemporal", "renderer.reuse.neighbors=0",
                                           "renderer.reuse.domain=distance", "renderer.reuse.target=fine",
                                           "renderer.reuse.distance_steps=256"],
                "distance_temporal_fine128": ["renderer.reuse.mode=spatiotemporal", "renderer.reuse.neighbors=0",
                                              "renderer.reuse.domain=distance", "renderer.reuse.target=fine",
                                              "renderer.reuse.distance_steps=128"],
                "distance_spatiotemporal_fine": ["renderer.reuse.mode=spatiotemporal", "renderer.reuse.domain=distance",
                                                 "renderer.reuse.target=fine", "renderer.reuse.distance_steps=256"],
                "distance_own_unshadowed": ["renderer.reuse.mode=spatial", "renderer.reuse.neighbors=0",
                                            "renderer.reuse.domain=distance"],
                "distance_spatiotemporal_unshadowed": ["renderer.reuse.mode=spatiotemporal",
                                                       "renderer.reuse.domain=distance"]}


def bench_nrc(name: str, args, log) -> dict:
    """1-spp NRC frames of a static camera (the reference of :func:`bench_scene`), one run per ``--nrc-variants``
    entry (:data:`NRC_VARIANTS`; ``none`` first, the baseline): per-frame relMSE, bias and the same after OIDN,
    frames after ``--nrc-warmup``; the frames' relative variance over time (per pixel, over the mean image
    squared + 0.01, medium pixels: the noise, with the cache's drift); gains against ``none`` per frame and at
    equal time (raw relMSE and variance scaled by the seconds per frame)."""

    base = nrc_overrides(name, args)
    ref = np.load(args.out / f"ref_{name}_{args.ref_spp}.npy")
    mask = medium(base)
    shared = str(REPO.parent / "shared")  # recorded as ../shared (relative to the repo), not this machine's path
    out: dict = {"scene": name, "renderer": "nrc", "overrides": [o.replace(shared, "../shared") for o in base],
                 "variants": {m: NRC_VARIANTS[m] for m in args.nrc_variants.split(",")}, "modes": {}}
    for mode in args.nrc_variants.split(","):
        frames = []
        res = renderer([*base, *NRC_VARIANTS[mode]]).render(on_frame=lambda f, img, o, st: frames.append(img))
        kept = np.stack(frames[args.nrc_warmup:])
        row = mean_score(kept, ref, mask)
        row["rel_var_frames"] = float((kept.var(0, ddof=1) / (kept.mean(0) ** 2 + 0.01))[mask].mean())
        # the frames' mean against the reference: the error no per-frame noise reduction removes (the cache's
        # bias, plus the mean's own noise, var / frames)
        row["rel_mse_of_mean"] = rel_mse(kept.mean(0), ref, mask)
        row["seconds_per_frame"] = float(np.median(res.metrics["frame_times_s"][args.nrc_warmup:]))
        row["seconds_reuse"] = float(np.median(res.metrics["history"].get("time_reuse_s", [0.0])[args.nrc_warmup:]
                                               or [0.0]))
        out["modes"][mode] = row
        log(f"nrc {name} {mode}: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()))
    no = out["modes"].get("none")
    for mode, st in out["modes"].items():
        if no is None or mode == "none":
            continue
        speed = no["seconds_per_frame"] / st["seconds_per_frame"]
        st["gain_raw_per_frame"] = no["rel_mse"] / st["rel_mse"]
        st["gain_raw_equal_time"] = st["gain_raw_per_frame"] * speed
        st["gain_oidn_per_frame"] = no["rel_mse_oidn"] / st["rel_mse_oidn"]
        st["gain_variance_equal_time"] = no["rel_var_frames"] / st["rel_var_frames"] * speed
    return out


DECOMPOSE_VARIANTS = [("spatial", "balance"), ("spatial", "pairwise"), ("spatiotemporal", "balance"),
                      ("spatiotemporal", "pairwise")]


def decompose_scene(spec: str, args, log) -> dict:
    """The variance decomposition of ``--decompose`` (module docstring) for ``name[:override,...]``."""
    import dataclasses

    from nrc.render.reuse import ReservoirReuse, VertexRecord

    name, extra = parse_spec(spec)
    passes = args.frames
    run = setup([*preset(name), *COMMON, *args.extra, *extra, "renderer.reuse.mode=spatial",
                 f"scene.integrator.spp={passes}", "scene.integrator.seed=1"])
    scene = run.scene
    pt = run.renderer()
    mask = medium_mask(medium_alpha(scene)).reshape(-1)
    cam, n, st = scene.camera, scene.camera.num_pixels, pt.settings
    gen = torch.Generator(device=pt.device).manual_seed(7)
    machine, _, _ = pt.core.choose(n)
    reusers = {f"{m}/{w}": ReservoirReuse(dataclasses.replace(st.reuse, mode=m, mis=w), scene.g, 1, scene.grid)
               for m, w in DECOMPOSE_VARIANTS}
    own = next(iter(reusers.values()))
    parts: dict[str, list] = {"A": [], "B": [], **{k: [] for k in reusers}}
    secs = {"trace": 0.0, "B": 0.0, **{k: 0.0 for k in reusers}}
    shade_args = (pt.transmittance, scene.grid, pt.majorants, gen, pt.shadow_batch)
    for j in range(passes):
        rec = VertexRecord.empty(n, st.reuse.vertex(scene.g), scene.albedo, pt.device)
        one = torch.zeros(n, 3, device=pt.device)
        t0 = time.perf_counter()
        pt.trace_pass(machine, gen, rec, j, passes, one)
        t1 = time.perf_counter()
        parts["B"].append(own.shade(own.initial(rec, pt.lights, gen), rec, pt.lights, *shade_args).cpu().numpy())
        secs["trace"] += t1 - t0
        secs["B"] += time.perf_counter() - t1
        parts["A"].append(one.cpu().numpy())
        for k, ru in reusers.items():
            t2 = time.perf_counter()
            parts[k].append(ru.frame(rec, cam, pt.lights, *shade_args)[0].cpu().numpy())
            secs[k] += time.perf_counter() - t2
    x = {k: np.stack(v)[args.warmup:] for k, v in parts.items()}
    den = (x["A"] + x["B"]).mean(0) ** 2 + 0.01

    def rel_var(v: np.ndarray) -> float:
        return float((v.var(0, ddof=1) / den)[mask].mean())

    def image_var(v: np.ndarray) -> float:  # brightness-weighted: summed variance over the summed mean squared
        return float(v.var(0, ddof=1)[mask].sum() / (den - 0.01)[mask].sum())

    mean_a, mean_b = float(x["A"].mean(0)[mask].mean()), float(x["B"].mean(0)[mask].mean())
    none = rel_var(x["A"] + x["B"])
    out = {"scene": spec, "passes_scored": passes - args.warmup, "direct_share": mean_b / (mean_a + mean_b),
           "rel_var_none": none, "rel_var_trace_only": rel_var(x["A"]), "ceiling": none / rel_var(x["A"]),
           "ceiling_image": image_var(x["A"] + x["B"]) / image_var(x["A"]), "rel_var_direct_own": rel_var(x["B"]), "s_per_pass_trace": secs["trace"] / passes,
           "s_per_pass_own": secs["B"] / passes, "variants": {}}
    for k in reusers:
        out["variants"][k] = {"rel_var_direct": rel_var(x[k]), "rel_var_frame": rel_var(x["A"] + x[k]),
                              "gain_direct": rel_var(x["B"]) / rel_var(x[k]),
                              "gain_frame": none / rel_var(x["A"] + x[k]),
                              "gain_direct_image": image_var(x["B"]) / image_var(x[k]),
                              "gain_frame_image": image_var(x["A"] + x["B"]) / image_var(x["A"] + x[k]),
                              "mean_direct_over_own": float(x[k].mean(0)[mask].mean()) / mean_b,
                              "s_per_pass": secs[k] / passes}
    log(f"decompose {spec}: direct share {out['direct_share']:.3f}, ceiling {out['ceiling']:.2f}x; " + ", ".join(
        f"{k} direct {v['gain_direct']:.2f}x frame {v['gain_frame']:.2f}x" for k, v in out["variants"].items()))
    return out


class _RecordingReuse:
    """Wraps the NRC renderer's :class:`ReservoirReuse`: each frame it also estimates the vertices' direct light
    by their own RIS (the ``none`` estimator, on a generator of its own, so the render and the cache's training
    are those of the run without the recording) and keeps both per pixel."""

    def __init__(self, inner, device) -> None:
        self.inner, self.gen = inner, torch.Generator(device=device).manual_seed(99)
        self.own: list[np.ndarray] = []
        self.reused: list[np.ndarray] = []
        self.s_own: list[float] = []

    def frame(self, rec, camera, lights, transmittance, grid, majorants, gen, batch):
        t0 = time.perf_counter()
        res = self.inner.frame_initial(rec, camera, lights, self.gen)
        own = self.inner.shade(res, rec, lights, transmittance, grid, majorants, self.gen, batch)
        self.s_own.append(time.perf_counter() - t0)
        out, stats = self.inner.frame(rec, camera, lights, transmittance, grid, majorants, gen, batch)
        self.own.append(own.cpu().numpy())
        self.reused.append(out.cpu().numpy())
        return out, stats

    def __getattr__(self, name):
        return getattr(self.inner, name)


def reference(name: str, base: list[str], args, log) -> np.ndarray:
    """The scene type's converged reference (``--ref-spp``, rendered once without reuse and kept in ``--out``)."""
    ref_path = args.out / f"ref_{name}_{args.ref_spp}.npy"
    if ref_path.is_file():
        return np.load(ref_path)
    log(f"{name}: reference, {args.ref_spp} spp")
    res, secs, _ = render([*base, f"scene.integrator.spp={args.ref_spp}", "scene.integrator.seed=900001"])
    np.save(ref_path, res.image)
    log(f"  {secs:.0f} s")
    return res.image


def decompose_nrc(name: str, args, log) -> dict:
    """``--decompose-nrc``: the decomposition for 1-spp NRC frames of a static camera. The render runs with
    ``spatiotemporal`` reuse; each frame's image minus the reuse pass's direct light is ``A`` (the rest of the
    render paths and the cache), to which the vertices' own-RIS direct light (``none``) or the reused one is
    added: the frames of both estimators on the same cache, scored against the reference (relMSE, the image mean,
    the same after OIDN) and by their variance over the frames (which includes the cache's drift)."""

    pt_base = [*preset(name), *COMMON, *args.extra]
    ref = reference(name, pt_base, args, log)
    run = setup(nrc_overrides(name, args, defaults=["renderer.reuse.mode=spatiotemporal"]))
    scene = run.scene
    mask = medium_mask(medium_alpha(scene))
    r = run.renderer()
    rec = r.reuse = _RecordingReuse(r.reuse, r.device)
    images, times, t_reuse = [], [], []

    def on_frame(f, img, output, stats):
        images.append(np.asarray(img).reshape(-1, 3).copy())
        times.append(stats.get("time_frame_s", float("nan")))
        t_reuse.append(stats.get("time_reuse_s", float("nan")))

    r.render(on_frame=on_frame)
    w = args.nrc_warmup
    img, own, reused = (np.stack(v)[w:] for v in (images, rec.own, rec.reused))
    rest = img - reused
    frames = {"none": rest + own, "spatiotemporal": img}
    hw = (scene.camera.height, scene.camera.width, 3)
    m = mask.reshape(-1)
    den = img.mean(0) ** 2 + 0.01

    def rel_var(v: np.ndarray) -> float:
        return float((v.var(0, ddof=1) / den)[m].mean())

    out: dict = {"scene": name, "renderer": "nrc", "frames_scored": len(img),
                 "direct_share": float(own.mean(0)[m].mean() / (rest.mean(0)[m].mean() + own.mean(0)[m].mean())),
                 "ceiling": rel_var(rest + own) / rel_var(rest), "modes": {}}
    # seconds per frame: the run's without the recording's own-RIS pass (it runs inside the frame's time);
    # none's replaces the reuse pass by that own-RIS pass
    s_own = float(np.median(rec.s_own[w:]))
    t_frame, t_st = float(np.median(times[w:])) - s_own, float(np.median(t_reuse[w:]))
    for mode, v in frames.items():
        row = mean_score(v.reshape(-1, *hw), ref, mask)
        row["rel_var_frames"] = rel_var(v)
        row["seconds_per_frame"] = t_frame if mode == "spatiotemporal" else t_frame - t_st + s_own
        out["modes"][mode] = row
        log(f"nrc decompose {name} {mode}: " + ", ".join(f"{k} {x:.4g}" for k, x in row.items()))
    no, st = out["modes"]["none"], out["modes"]["spatiotemporal"]
    st["gain_variance_per_frame"] = no["rel_var_frames"] / st["rel_var_frames"]
    st["gain_variance_equal_time"] = st["gain_variance_per_frame"] * no["seconds_per_frame"] / st["seconds_per_frame"]
    st["gain_rel_mse_per_frame"] = no["rel_mse"] / st["rel_mse"]
    st["gain_rel_mse_oidn_per_frame"] = no["rel_mse_oidn"] / st["rel_mse_oidn"]
    return out


ORACLE_REUSE = "distance_spatiotemporal_fine"


def oracle_nrc(spec: str, args, log) -> dict:
    """``--oracle-nrc``: what the best possible reuse of the distance domain could give. For
    ``name[:override,...]`` (``renderer.debias.probability=q`` among them: ``q = 0`` the biased NRC, ``q = 1``
    the path tracer's estimator) two NRC runs of 1-spp frames of a static camera on the same overrides:
    ``none`` (no reuse), and :data:`ORACLE_REUSE`, whose reuse pass is recorded with the pixels' own RIS of the
    same term beside it (:class:`_RecordingReuse`). With ``domain=distance`` that term is ``I``, the camera
    ray's single scattering of the sampled lights, which does not depend on the path or the cache; ``rest`` is
    the frame minus it. Four estimators are scored per frame against the reference (relMSE, mean, FLIP, the
    same after OIDN): ``none``; ``own`` (``rest`` + own RIS); the reuse run's frame; and ``oracle``: ``rest``
    plus the mean over the scored frames of both estimates of ``I`` (a noiseless ``I`` up to ``1/(2 frames)``
    of its variance) at no cost, which no reuse of the distance domain can beat. Equal time: raw relMSE scaled
    by the seconds per frame (the oracle's are the reuse run's without its reuse pass)."""

    name, extra = parse_spec(spec)
    # the reference depends on the scene only: the spec's scene.* overrides go into it (and its file name)
    scene_extra = [o for o in extra if o.startswith("scene.")]
    tag = f"{name}_{zlib.crc32(' '.join(scene_extra).encode()):08x}" if scene_extra else name
    ref = reference(tag, [*preset(name), *COMMON, *args.extra, *scene_extra], args, log)
    base = nrc_overrides(name, args, extra)
    w = args.nrc_warmup
    scene = setup(base).scene
    mask = medium_mask(medium_alpha(scene))
    hw = (scene.camera.height, scene.camera.width, 3)
    runs = {}
    for variant in ("none", ORACLE_REUSE):
        r = renderer([*base, *NRC_VARIANTS[variant]])
        rec = r.reuse = _RecordingReuse(r.reuse, r.device) if r.reuse is not None else None
        images: list[np.ndarray] = []
        res = r.render(on_frame=lambda f, img, o, st: images.append(np.asarray(img).reshape(-1, 3).copy()))
        hist = res.metrics["history"]
        runs[variant] = {"img": np.stack(images)[w:], "rec": rec,
                         "s": float(np.median(res.metrics["frame_times_s"][w:])),
                         "s_reuse": float(np.median(hist.get("time_reuse_s", [0.0])[w:] or [0.0]))}
        log(f"oracle {spec} {variant}: {runs[variant]['s']:.2f} s/frame")
    run = runs[ORACLE_REUSE]
    own, reused = (np.stack(v)[w:] for v in (run["rec"].own, run["rec"].reused))
    rest = run["img"] - reused
    exact = 0.5 * (own.mean(0) + reused.mean(0))
    # the recording's own-RIS pass runs inside the frame's time: the reuse run's frame is that time without it
    s_own = float(np.median(run["rec"].s_own[w:]))
    s_frame = run["s"] - s_own
    s_rest = s_frame - run["s_reuse"]
    estimators = {"none": (runs["none"]["img"], runs["none"]["s"]), "own": (rest + own, s_rest + s_own),
                  "reuse": (run["img"], s_frame), "oracle": (rest + exact[None], s_rest)}
    m = mask.reshape(-1)
    out: dict = {"scene": spec, "renderer": "nrc", "reuse": NRC_VARIANTS[ORACLE_REUSE], "frames_scored": len(own),
                 "single_scatter_share": float(exact[m].mean() / run["img"].mean(0)[m].mean()), "estimators": {}}
    for key, (frames, secs) in estimators.items():
        row = mean_score(frames.reshape(-1, *hw), ref, mask)
        row["rel_mse_of_mean"] = rel_mse(frames.mean(0).reshape(hw), ref, mask)
        row["seconds_per_frame"] = secs
        out["estimators"][key] = row
        log(f"oracle {spec} {key}: " + ", ".join(f"{k} {x:.4g}" for k, x in row.items()))
    no = out["estimators"]["none"]
    for key, row in out["estimators"].items():
        row["gain_raw_per_frame"] = no["rel_mse"] / row["rel_mse"]
        row["gain_raw_equal_time"] = row["gain_raw_per_frame"] * no["seconds_per_frame"] / row["seconds_per_frame"]
        row["gain_oidn_per_frame"] = no["rel_mse_oidn"] / row["rel_mse_oidn"]
    return out


def oracle_markdown(results: list[dict], meta: dict) -> str:
    lines = ["# Reservoir reuse: the oracle bound (`scripts/bench_reuse.py --oracle-nrc`)", "",
             f"{meta['machine']}; torch {meta['torch']}; code {meta['code']}; {meta['nrc_frames']} frames, first "
             f"{meta['nrc_warmup']} left out; reference {meta['ref_spp']} spp; extra: {' '.join(meta['extra']) or '-'}",
             "", "`oracle`: the frame with the camera ray's single scattering of the lights replaced by its "
             "expectation, at no cost (the best any reuse of the distance domain can do). `own`/`reuse`: the "
             f"distance domain's own RIS / `{ORACLE_REUSE}`. Gains against `none` (no reuse); equal time scales "
             "the raw relMSE by the seconds per frame; OIDN per frame.", "",
             "| scene | single-scatter share | estimator | s/frame | relMSE | mean/ref | relMSE OIDN | mean/ref OIDN | "
             "relMSE of mean | gain raw: per frame / equal time | gain OIDN per frame |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        for i, (key, row) in enumerate(r["estimators"].items()):
            head = f"| {r['scene']} | {r['single_scatter_share']:.3f}" if i == 0 else "| |"
            g = "–" if key == "none" else f"{row['gain_raw_per_frame']:.2f}x / {row['gain_raw_equal_time']:.2f}x"
            go = "–" if key == "none" else f"{row['gain_oidn_per_frame']:.2f}x"
            lines.append(f"{head} | {key} | {row['seconds_per_frame']:.2f} | {row['rel_mse']:.4g} | "
                         f"{row['mean_ratio']:.3f} | {row['rel_mse_oidn']:.4g} | {row['mean_ratio_oidn']:.3f} | "
                         f"{row['rel_mse_of_mean']:.4g} | {g} | {go} |")
    return "\n".join(lines) + "\n"


def decompose_nrc_markdown(results: list[dict]) -> str:
    lines = ["", "## NRC frames (`--decompose-nrc`): the two estimators of the first vertex's direct light on one "
             "cache", "", "| scene | frames | direct share | ceiling | estimator | s/frame | relMSE | mean/ref | "
             "relMSE OIDN | mean/ref OIDN | relVar over frames | gain: variance per frame / at equal time | "
             "gain: relMSE / relMSE OIDN per frame |", "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        for i, (mode, row) in enumerate(r["modes"].items()):
            head = f"| {r['scene']} | {r['frames_scored']} | {r['direct_share']:.3f} | {r['ceiling']:.2f}x" \
                if i == 0 else "| | | |"
            g1 = (f"{row['gain_variance_per_frame']:.2f}x / {row['gain_variance_equal_time']:.2f}x"
                  if "gain_variance_per_frame" in row else "-")
            g2 = (f"{row['gain_rel_mse_per_frame']:.2f}x / {row['gain_rel_mse_oidn_per_frame']:.2f}x"
                  if "gain_rel_mse_per_frame" in row else "-")
            lines.append(f"{head} | {mode} | {row['seconds_per_frame']:.3f} | {row['rel_mse']:.4g} | "
                         f"{row['mean_ratio']:.4f} | {row['rel_mse_oidn']:.4g} | {row['mean_ratio_oidn']:.4f} | "
                         f"{row['rel_var_frames']:.4g} | {g1} | {g2} |")
    return "\n".join(lines) + "\n"


def decompose_markdown(results: list[dict], meta: dict) -> str:
    lines = ["# Reservoir reuse: where a 1-spp frame's variance is (`scripts/bench_reuse.py --decompose`)", "",
             f"{meta['machine']}; torch {meta['torch']}; code {meta['code']}; {meta['frames']} passes, first "
             f"{meta['warmup']} left out; extra: {' '.join(meta['extra']) or '-'}", "",
             "Relative variances (per pixel over the passes, over the mean image squared + 0.01, averaged over the "
             "medium). `direct`: the reuse vertex's direct light; ceiling: the frame's variance over that of the "
             "frame without it (a noiseless direct-light estimate). Gains are variance ratios per frame against "
             "the vertex's own RIS (`none`), at the same vertices; times per 1-spp pass. `image`: the same gains "
             "brightness-weighted (summed variance over the summed mean squared), which bright pixels dominate.", "",
             "| scene | direct share | relVar frame (none) | ceiling (image) | variant | direct: relVar (gain) | "
             "frame: relVar (gain) | gain image: direct / frame | mean direct / none | s/pass (trace + reuse) |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in results:
        for i, (k, v) in enumerate(r["variants"].items()):
            head = (f"| {r['scene']} | {r['direct_share']:.3f} | {r['rel_var_none']:.4g} | {r['ceiling']:.2f}x "
                    f"({r['ceiling_image']:.2f}x)" if i == 0 else "| | | |")
            lines.append(f"{head} | {k} | {v['rel_var_direct']:.4g} ({v['gain_direct']:.2f}x) | "
                         f"{v['rel_var_frame']:.4g} ({v['gain_frame']:.2f}x) | {v['gain_direct_image']:.2f}x / "
                         f"{v['gain_frame_image']:.2f}x | {v['mean_direct_over_own']:.3f} | "
                         f"{r['s_per_pass_trace']:.2f} + {v['s_per_pass']:.2f} |")
        lines.append(f"| | | | | none (own RIS) | {r['rel_var_direct_own']:.4g} | {r['rel_var_none']:.4g} | 1 / 1 | 1 | "
                     f"{r['s_per_pass_trace']:.2f} + {r['s_per_pass_own']:.2f} |")
    return "\n".join(lines) + "\n"


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"# Reservoir reuse: 1-spp frames ({meta['frames']} frames, first {meta['warmup']} left out)", "",
             f"{meta['machine']}; torch {meta['torch']}; code {meta['code']}; extra: {' '.join(meta['extra']) or '-'}", "",
             "| scene | mode | s/frame | relMSE | mean/ref | FLIP | relMSE OIDN | mean/ref OIDN | FLIP OIDN | "
             "equal-time gain raw | equal-time gain OIDN |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    nrc = [r for r in results if r.get("renderer") == "nrc"]
    for r in results:
        if r in nrc:
            continue
        for mode, row in r["modes"].items():
            g1 = row.get("gain_raw_equal_time")
            if "gain_oidn_per_frame" in row:  # nrc: no equal-time none render
                g2 = f"{row['gain_oidn_per_frame']:.2f}x per frame"
            elif "gain_oidn_equal_time" in row:
                g2 = f"{row['gain_oidn_equal_time']:.2f}x (none at {row['equal_time_spp_none']} spp)"
            else:
                g2 = "-"
            lines.append(f"| {r['scene']} ({r.get('renderer', 'pt')}) | {mode} | {row['seconds_per_frame']:.3f} | "
                         f"{row['rel_mse']:.4g} | {row['mean_ratio']:.4f} | {row['flip']:.4f} | "
                         f"{row['rel_mse_oidn']:.4g} | {row['mean_ratio_oidn']:.4f} | {row['flip_oidn']:.4f} | "
                         f"{'-' if g1 is None else f'{g1:.2f}x'} | {g2} |")
    if nrc:
        lines += ["", f"## NRC, 1-spp frames of a static camera ({meta['nrc_frames']} frames, first "
                  f"{meta['nrc_warmup']} left out; gains against `none`)", "",
                  "| scene | variant | s/frame | reuse pass s | relMSE | mean/ref | relMSE OIDN | mean/ref OIDN | "
                  "relVar over frames | relMSE of the frames' mean | gain relMSE per frame / equal time | "
                  "gain relVar equal time | gain relMSE OIDN per frame |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in nrc:
            for mode, row in r["modes"].items():
                g = (f"{row['gain_raw_per_frame']:.2f}x / {row['gain_raw_equal_time']:.2f}x | "
                     f"{row['gain_variance_equal_time']:.2f}x | {row['gain_oidn_per_frame']:.2f}x"
                     if "gain_raw_per_frame" in row else "- | - | -")
                lines.append(f"| {r['scene']} | {mode} | {row['seconds_per_frame']:.3f} | {row['seconds_reuse']:.3f} | "
                             f"{row['rel_mse']:.4g} | {row['mean_ratio']:.4f} | {row['rel_mse_oidn']:.4g} | "
                             f"{row['mean_ratio_oidn']:.4f} | {row['rel_var_frames']:.4g} | "
                             f"{row.get('rel_mse_of_mean', float('nan')):.4g} | {g} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="many_lights,side_lit")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--equal-time-frames", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=512)
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "bench_reuse")
    ap.add_argument("--extra", nargs="*", default=[])
    ap.add_argument("--nrc", default="", help="scene types to run NRC frames on too (static camera)")
    ap.add_argument("--nrc-variants", default="none,spatiotemporal",
                    help=f"--nrc runs, comma-separated, none first: {', '.join(NRC_VARIANTS)}")
    ap.add_argument("--nrc-frames", type=int, default=16)
    ap.add_argument("--nrc-warmup", type=int, default=8)
    ap.add_argument("--decompose", default="", help="scene types (name or name:override,override; ';' between "
                    "them) to decompose the variance of instead (module docstring)")
    ap.add_argument("--decompose-nrc", default="", help="scene types to decompose NRC frames of (module "
                    "docstring; uses --nrc-frames, --nrc-warmup and the reference)")
    ap.add_argument("--oracle-nrc", default="", help="scene types (name or name:override,override; ';' between "
                    "them) to bound the distance domain's reuse on (oracle_nrc; uses --nrc-frames, --nrc-warmup)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(msg, flush=True)

    meta = {"frames": args.frames, "warmup": args.warmup, "nrc_frames": args.nrc_frames,
            "nrc_warmup": args.nrc_warmup, "ref_spp": args.ref_spp, "extra": args.extra, "code": code_version(),
            "torch": torch.__version__, "machine": machine()}
    if args.oracle_nrc:
        results = [oracle_nrc(s, args, log) for s in args.oracle_nrc.split(";") if s]
        (args.out / "oracle.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
        md = oracle_markdown(results, meta)
        (args.out / "oracle.md").write_text(md)
        print(md)
        return 0
    if args.decompose or args.decompose_nrc:
        results = [decompose_scene(s, args, log) for s in args.decompose.split(";") if s]
        nrc = [decompose_nrc(s, args, log) for s in args.decompose_nrc.split(",") if s]
        (args.out / "decompose.json").write_text(json.dumps({"meta": meta, "results": results, "nrc": nrc}, indent=1))
        md = (decompose_markdown(results, meta) if results else "") + (decompose_nrc_markdown(nrc) if nrc else "")
        (args.out / "decompose.md").write_text(md)
        print(md)
        return 0

    results = [bench_scene(s, args, log) for s in args.scenes.split(",") if s]
    results += [bench_nrc(s, args, log) for s in args.nrc.split(",") if s]
    (args.out / "bench.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    (args.out / "bench.md").write_text(markdown(results, meta))
    print(markdown(results, meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
