"""Renders for the measurements: the one sequence compose -> load the scene -> build its renderer
(:func:`setup`, :func:`renderer`), and the timed renders of a loaded scene the equal-time measurements share
(:func:`pt_render`, :func:`nrc_run` and their untimed warm-ups). Renderers are built through the product's registry
(``nrc.render.registry.make_renderer``), never by their classes."""

from __future__ import annotations

import dataclasses
import sys
import time
from typing import Any, Callable, Sequence

import numpy as np
from omegaconf import DictConfig, open_dict

from nrc.config import absolute_paths, compose, resolve_device
from nrc.render.registry import make_renderer
from nrc.scene import Scene, load_scene

SEED_BASE = 1000  # seeds of the scored renders; references use seeds >= 1e6 (nrc.evaluation.reference.REF_SEED)
RUN_SEED_STRIDE = 7919  # run k of a repeated NRC measurement: seed base + stride * (k + 1), its frames' seeds apart
# from run k+1's (a frame's seed is the run's plus the frame index)


def run_seeds(runs: int, base: int = SEED_BASE) -> list[int]:
    """The base seeds of ``runs`` independent runs (:data:`RUN_SEED_STRIDE` apart)."""
    return [base + RUN_SEED_STRIDE * (k + 1) for k in range(runs)]


@dataclasses.dataclass
class Setup:
    """A composed config and its loaded scene."""

    cfg: DictConfig
    scene: Scene

    def renderer(self, scene: Scene | None = None) -> Any:
        """The config's renderer of ``scene`` (default: the loaded one), built by the product's registry."""
        return make_renderer(self.cfg.renderer.name, self.scene if scene is None else scene, self.cfg)


def setup(overrides: Sequence[str], frames: int | None = None, absolute: bool = False) -> Setup:
    """Compose ``overrides`` (``frames``: set the config's frame count; ``absolute``: resolve its relative file
    paths against the current directory, ``nrc.config.absolute_paths``) and load the scene on the config's
    device."""
    cfg = compose(list(overrides))
    if frames is not None:
        with open_dict(cfg):
            cfg.frames = int(frames)
    if absolute:
        absolute_paths(cfg)
    return Setup(cfg, load_scene(cfg.scene, resolve_device(cfg.device)))


def renderer(overrides: Sequence[str], frames: int | None = None, absolute: bool = False) -> Any:
    """The renderer ``overrides`` configure, of its freshly loaded scene (:func:`setup`)."""
    return setup(overrides, frames, absolute).renderer()


def render(overrides: Sequence[str], **kwargs: Any) -> Any:
    """One render of the renderer ``overrides`` configure (``kwargs`` to its ``render``); the result."""
    return renderer(overrides).render(**kwargs)


def with_spp_seed(scene: Scene, spp: int, seed: int) -> Scene:
    """``scene`` with ``spp`` samples per pixel and the base seed ``seed``."""
    return dataclasses.replace(scene, integrator=dataclasses.replace(scene.integrator, spp=int(spp), seed=int(seed)))


def warmup_scene(scene: Scene) -> Scene:
    """``scene`` with a 16 x 9 camera, for the untimed warm-up renders."""
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=16, height=9))


CPU_TIMES: list[float] = []  # process CPU time of each pt_render call (all threads), read by the callers
PT_METRICS: dict[str, Any] = {}  # the metrics of the last pt_render call (its backend, ...)


def pt_render(scene: Scene, cfg: DictConfig, spp: int, seed: int) -> tuple[np.ndarray, float]:
    """A path-traced render of ``scene`` (``cfg``'s path tracer settings) at ``spp`` spp with ``seed`` (non-finite
    values 0) and its wall time; its process CPU time is appended to :data:`CPU_TIMES`, its metrics kept in
    :data:`PT_METRICS`."""
    cfg.scene.integrator.spp, cfg.scene.integrator.seed = int(spp), int(seed)
    t0, c0 = time.perf_counter(), time.process_time()
    result = make_renderer("pt", with_spp_seed(scene, spp, seed), cfg).render(progress=False)
    CPU_TIMES.append(time.process_time() - c0)
    dt = time.perf_counter() - t0
    PT_METRICS.clear()
    PT_METRICS.update(result.metrics)
    return np.nan_to_num(result.image), dt


def pt_warmup(scene: Scene, cfg: DictConfig) -> None:
    """One untimed 16 x 9, 1-spp render: first-use costs of the ops (and of a compiled backend, if chosen)."""
    pt_render(warmup_scene(scene), cfg, 1, SEED_BASE - 1)


def nrc_run(scene: Scene, cfg: DictConfig, spp: int, seed: int, frames: int, accumulate: bool,
            on_frame: Callable[[int, np.ndarray, np.ndarray, dict], None]) -> Any:
    """Run the NRC renderer for ``frames`` frames, calling ``on_frame(frame, image, accumulated, stats)``;
    returns its :class:`~nrc.render.result.RenderResult`. A SIGINT or SIGTERM (which the renderer takes to stop
    after the current frame) ends the lab tool here with one line and the signal's exit code (130 / 143), instead
    of a tool scoring frames that were never rendered."""
    with open_dict(cfg):
        cfg.frames = int(frames)
        cfg.renderer.accumulate = bool(accumulate)
        cfg.scene.integrator.spp, cfg.scene.integrator.seed = int(spp), int(seed)
    result = make_renderer("nrc", with_spp_seed(scene, spp, seed), cfg).render(progress=False, on_frame=on_frame)
    stopped_by(result.metrics, frames)
    return result


def stopped_by(metrics: dict, frames: int) -> None:
    """Exit (130 for SIGINT, 143 for SIGTERM) with one line where an NRC run's ``metrics`` say a signal stopped it."""
    sig = metrics.get("interrupted")
    if sig:
        print(f"{sys.argv[0]}: stopped by {sig} after {metrics.get('frames_done', '?')} of {frames} NRC frames; "
              "nothing of the unfinished run is written", file=sys.stderr)
        raise SystemExit(130 if sig == "SIGINT" else 143)


def nrc_warmup(scene: Scene, cfg: DictConfig) -> float:
    """One untimed 16 x 9, 1-frame NRC run (as :func:`pt_warmup`): the compile, or its load from the persistent
    cache, happens here, not in the first scored frame; returns its wall time (reported as ``startup_s``)."""
    t0 = time.perf_counter()
    nrc_run(warmup_scene(scene), cfg.copy(), 1, SEED_BASE - 1, 1, False, lambda *a: None)
    return time.perf_counter() - t0
