"""nrc from Python: render a scene from overrides and get the image, the metrics and the config (``nrc.run``,
``nrc.frames``, ``nrc.load_config``; ``nrc.render`` is the renderers' package, so the call that renders is ``run``,
as ``python -m nrc`` runs one).

    import nrc
    r = nrc.run(["scene=thick", "scene.camera.width=160", "scene.camera.height=90"])   # or a dict
    r.image            # (H, W, 3) float32, linear RGB (numpy); r.denoised with denoise=oidn (the default)
    r.metrics          # what metrics.json holds;  r.config: the resolved config (OmegaConf)
    for f in nrc.frames({"renderer": "nrc", "frames": 30}):   # NRC frame by frame: the cache learning
        print(f.index, f.stats["loss"])                       # stop whenever you like (break)

The same code as ``python -m nrc`` (:func:`nrc.app.execute`): with the same overrides, seed, ``renderer.backend``
and ``threads`` the image is bitwise the same. Nothing is written unless ``out_dir`` is given (then the run
directory of ``python -m nrc``: image.exr, preview.png, metrics.json, and for NRC TensorBoard logs and the
checkpoint). Every error a user can cause is an :class:`nrc.errors.NRCError` naming what is wrong: Hydra's
composition errors (an unknown key, a bad group) come as :class:`~nrc.errors.ConfigError`.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

import numpy as np

from nrc.errors import ConfigError, NRCError

Overrides = Union[Sequence[str], Mapping[str, Any], None]


@dataclass
class Render:
    """A finished render: ``image`` (H, W, 3) float32 linear RGB; ``denoised`` (with ``denoise=oidn``) or None;
    ``metrics`` (``metrics.json``'s content); ``config`` the resolved config; ``out_dir`` where the outputs were
    written, or None."""

    image: np.ndarray
    denoised: np.ndarray | None
    metrics: dict[str, Any]
    config: Any
    out_dir: Path | None


@dataclass
class Frame:
    """One NRC frame: ``index`` (from 0), ``image`` this frame's render, ``output`` what the run shows after it
    (the frame, or the running mean with ``renderer.accumulate=true``), ``stats`` its numbers (loss, times, ...);
    both images (H, W, 3) float32 linear RGB."""

    index: int
    image: np.ndarray
    output: np.ndarray
    stats: dict[str, Any]


def _value(v: Any) -> str:
    """An override's value as Hydra's grammar reads it."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_value(x) for x in v) + "]"
    return str(v)  # numbers, strings, paths


def as_overrides(overrides: Overrides) -> list[str]:
    """``["key=value", ...]`` from a list of override strings or a ``{key: value}`` dict (values may be numbers,
    booleans, None, lists or strings; a config group takes its option's name, e.g. ``{"scene": "thick"}``)."""
    if overrides is None:
        return []
    if isinstance(overrides, str):
        raise ConfigError(f"overrides must be a list of 'key=value' strings or a dict, got the string {overrides!r}")
    if isinstance(overrides, Mapping):
        return [f"{k}={_value(v)}" for k, v in overrides.items()]
    out = []
    for o in overrides:
        if not isinstance(o, str):
            raise ConfigError(f"an override must be a 'key=value' string, got {o!r}")
        out.append(o)
    return out


def load_config(overrides: Overrides = None) -> Any:
    """The resolved config for ``overrides``, as ``python -m nrc`` composes it (file paths made absolute against
    the current directory); Hydra's errors as :class:`ConfigError`."""
    from nrc.config import absolute_paths, compose

    lines = as_overrides(overrides)
    try:
        cfg = compose(lines)
    except Exception as exc:  # Hydra's and OmegaConf's errors (composition, override grammar) become ours
        if isinstance(exc, NRCError) or type(exc).__module__.split(".")[0] not in ("hydra", "omegaconf"):
            raise
        text = " ".join(str(exc).split()).split(" Config search path:")[0]
        raise ConfigError(f"overrides {lines}: {text}") from None
    absolute_paths(cfg)
    return cfg


def run(overrides: Overrides = None, *, out_dir: str | Path | None = None, progress: bool = False) -> Render:
    """Render the scene ``overrides`` configure with its renderer (``renderer=pt|nrc|preview``) and return the
    image, the denoised image, the metrics and the config; with ``out_dir`` the outputs of ``python -m nrc`` are
    written there."""
    from nrc.app import execute

    cfg = load_config(overrides)
    out = None if out_dir is None else Path(out_dir)
    outcome = execute(cfg, out, progress=progress)
    return Render(outcome.image, outcome.denoised, outcome.metrics, cfg, out)


def frames(overrides: Overrides = None, *, out_dir: str | Path | None = None) -> Iterator[Frame]:
    """NRC frame by frame (``renderer=nrc`` is implied): yields each frame of ``frames`` as it is rendered (the
    renderer's own frame loop, ``NRCRenderer.frame_loop``, run in the caller's thread between the yields: the same
    code, thread and settings as ``python -m nrc``); leaving the loop early stops the render after that frame. The
    frames are those of ``python -m nrc renderer=nrc`` (the last one bitwise). With ``out_dir`` the run's logs and
    checkpoints go there as the frames are rendered, and once the last frame is done its outputs too
    (``image.exr``, ``preview.png``, ``metrics.json``: those of ``python -m nrc``); a loop left early writes no
    final outputs."""
    from nrc.app import prepare

    lines = as_overrides(overrides)
    if not any(o.split("=", 1)[0].lstrip("+") == "renderer" for o in lines):
        lines = ["renderer=nrc", *lines]
    cfg = load_config(lines)
    if cfg.renderer.get("name") != "nrc":
        raise ConfigError(f"nrc.frames renders renderer=nrc, got renderer={cfg.renderer.get('name')}")
    job = prepare(cfg, None if out_dir is None else Path(out_dir))
    return _frame_iterator(job)


def _frame_iterator(job: Any) -> Iterator[Frame]:
    """The frames of ``job``'s frame loop; its outputs written (with ``job.out_dir``) once the last is done. The
    loop runs here, in the consumer's thread, not in a helper thread: a thread of its own renders with other
    per-thread state (glibc serves a second thread's large temporaries from an arena that maps them afresh, page
    faults the main arena spares: an eager 48x27 frame of scene=thick took 1.3x as long; torch's grad mode is per
    thread too)."""
    from nrc.app import finish

    loop = job.renderer.frame_loop()
    try:
        while True:
            try:
                index, image, output, stats = next(loop)
            except StopIteration as end:
                if job.out_dir is not None:  # the outputs of python -m nrc, once the last frame is done
                    finish(job, end.value)
                return
            yield Frame(index, image, output.copy(), dict(stats))
    finally:
        loop.close()  # a loop left early: the render stops after the frame it has (its training thread ended)
