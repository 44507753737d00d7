"""Settings of ``renderer=nrc`` read from the ``renderer`` block (``conf/renderer/nrc.yaml``), validated.

Every key is checked (type and range) and unknown keys are errors naming the key, like the cache's
config blocks (:class:`nrc.config.ConfigReader`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from nrc.config import ConfigReader
from nrc.errors import ConfigError
from nrc.render.radiance_caching.debias import DebiasSettings
from nrc.render.radiance_caching.termination import Termination
from nrc.render.reuse import ReuseSettings
from nrc.render.wavefront.step import RussianRoulette
from nrc.scene import ANIMATIONS
from nrc.transport.light_sampling import LightSamplingSettings

CACHE_TARGETS = ("full", "indirect")


@dataclass(frozen=True)
class TrainingSettings:
    width: int | None  # training image width (training paths per row); None: auto (sized to the medium)
    height: int | None  # training image height; None: auto
    records_per_path: int  # V
    extra_vertices: int  # vertices a training path goes past the render path's stop
    unbiased_fraction: float | None  # probability that a training path never terminates into the cache; None: auto
    unbiased_max_vertices: int  # ... until this vertex after all (0: never; it runs to max_scatter)
    ring_buffer: int | None  # records kept from earlier frames; None: auto (ring_size: RING_FRAMES frames of the records a frame leaves)
    carry_frames: int = 0  # later frames a training path still going at its frame's end may go on in (0: the frame
    # waits for it; in the last one it ends into the cache at its next vertex)
    query_weights: str = "raw"  # cache weights of the training paths' terminal queries: ema | raw
    overlap: bool = False  # CPU: a frame's training steps run on a second thread during the next frame's one-thread
    # tail (nrc.render.radiance_caching.trainer); False: at the frame's end, on every thread
    paths_per_pixel: float = 1.0  # auto: training paths per pixel that sees the medium
    min_paths: int = 4096  # auto: the floor
    max_paths: int = 40960  # auto: the cap
    unbiased_warmup_frames: int = 0  # frames over which the unbiased fraction falls from 1 to unbiased_fraction

    def unbiased_fraction_at(self, frame: int) -> float:
        """The unbiased fraction of ``frame``'s training paths: 1 at frame 0, falling linearly to
        ``unbiased_fraction`` at frame ``unbiased_warmup_frames`` and staying there (0 warm-up frames: always
        ``unbiased_fraction``). An untrained cache's self-training targets pass its error on; an unbiased path's
        target does not (docs/measurements/learning.md, "A loss for unbiased targets": measured, not adopted)."""
        if self.unbiased_fraction is None:
            raise ValueError("unbiased_fraction: auto is resolved by the renderer (settings.resolve_auto)")
        if frame >= self.unbiased_warmup_frames:
            return self.unbiased_fraction
        return 1.0 - (1.0 - self.unbiased_fraction) * frame / self.unbiased_warmup_frames

    @property
    def auto(self) -> bool:
        return self.width is None

    @property
    def n_paths(self) -> int:
        if self.width is None or self.height is None:
            raise ValueError("the auto training image is sized by the renderer (training_set.auto_training_size)")
        return self.width * self.height


@dataclass(frozen=True)
class NRCSettings:
    """Validated ``renderer`` block of the NRC renderer (key meanings in ``conf/renderer/nrc.yaml``)."""

    slots: int
    shadow_batch: int
    backend: str
    steps_per_call: int
    compile_min_samples: int
    cuda_graphs: bool  # the step's calls through CUDA graphs of padded slot buckets (nrc.render.wavefront.graphs)
    brick: int | str
    free_flight: str
    termination: Termination
    cache_target: str  # full | indirect (nrc.render.radiance_caching.paths)
    terminal_nee: str  # mis | light: a terminating vertex's estimate of the sky (nrc.render.radiance_caching.vertex)
    light_sampling: LightSamplingSettings  # light_selection, ris.candidates, point_light_sampling
    reuse: ReuseSettings  # reservoir reuse at the render paths' first vertex (nrc.render.reuse)
    debias: DebiasSettings  # the cache as a control variate (nrc.render.radiance_caching.debias)
    training: TrainingSettings
    inference_batch: int
    accumulate: bool
    animate: str
    degrees_per_frame: float
    tensorboard: bool
    image_every: int
    checkpoint_every: int
    checkpoint_seconds: float | None
    reference: str | None
    resume: str | None
    roulette: RussianRoulette | None = None  # throughput roulette of the long paths (unbiased training paths, suffixes)

    @property
    def inline_shadows(self) -> bool:
        """Compiled, with ratio tracking: shadow rays inside the step, alongside the free flight
        (:func:`nrc.render.wavefront.build_core`)."""
        return True

    @classmethod
    def from_config(cls, renderer: Any) -> NRCSettings:
        cfg = ConfigReader(renderer, "renderer")
        cfg.get_choice("name", ["nrc"])
        tr, inf, anim, log = cfg.block("training"), cfg.block("inference"), cfg.block("animate"), cfg.block("log")
        enabled, roulette = RussianRoulette.from_config(cfg)
        settings = cls(
            slots=cfg.get_int("slots", lo=1),
            shadow_batch=cfg.get_int("shadow_batch", lo=1),
            backend=cfg.get_choice("backend", ["auto", "eager", "compiled"]),
            steps_per_call=cfg.get_int("steps_per_call", lo=1),
            compile_min_samples=cfg.get_int("compile_min_samples", lo=0),
            cuda_graphs=cfg.get_bool("cuda_graphs"),
            brick=cfg.get_raw("brick"),  # validated by nrc.render.wavefront.wavefront_majorants
            free_flight=cfg.get_choice("free_flight", ["brick", "global"]),
            termination=Termination.from_config(cfg.block("termination")),
            cache_target=cfg.get_choice("cache_target", CACHE_TARGETS),
            terminal_nee=cfg.get_choice("terminal_nee", ["mis", "light"]),
            light_sampling=LightSamplingSettings.from_config(cfg),
            reuse=ReuseSettings.from_config(cfg),
            debias=DebiasSettings.from_config(cfg),
            training=TrainingSettings(
                **_training_size(tr),
                records_per_path=tr.get_int("records_per_path", lo=1),
                extra_vertices=tr.get_int("extra_vertices", lo=0),
                unbiased_fraction=_unbiased_fraction(tr),
                unbiased_max_vertices=tr.get_int("unbiased_max_vertices", lo=0),
                unbiased_warmup_frames=tr.get_int("unbiased_warmup_frames", 0, lo=0),
                ring_buffer=_ring_buffer(tr),
                carry_frames=_carry_frames(tr),
                query_weights=tr.get_choice("query_weights", ["raw", "ema"]),
                overlap=tr.get_bool("overlap"),
                paths_per_pixel=tr.get_float("paths_per_pixel", lo=0.0, lo_open=True),
                min_paths=tr.get_int("min_paths", lo=1),
                max_paths=tr.get_int("max_paths", lo=1),
            ),
            inference_batch=inf.get_int("batch_size", lo=1),
            accumulate=cfg.get_bool("accumulate"),
            animate=anim.get_choice("mode", ANIMATIONS),
            degrees_per_frame=anim.get_float("degrees_per_frame"),
            tensorboard=log.get_bool("tensorboard"),
            image_every=log.get_int("image_every", lo=0),
            **_checkpoint_cadence(cfg),
            reference=cfg.get_optional_str("reference"),
            resume=cfg.get_optional_str("resume"),
            roulette=roulette if enabled else None,
        )
        for block in (tr, inf, anim, log, cfg):
            block.finish()
        t = settings.training
        if t.min_paths > t.max_paths:
            raise ConfigError(f"renderer.training.min_paths={t.min_paths} exceeds max_paths={t.max_paths}")
        if settings.reuse.light_only and settings.cache_target != "indirect":
            raise ConfigError("renderer.reuse.domain=distance needs renderer.cache_target=indirect (with full, a path "
                              "terminating at its first vertex counts that vertex's direct light in the cache's answer)")
        if settings.accumulate and settings.animate != "none":
            raise ConfigError(f"renderer.accumulate=true averages the frames of a static scene; it cannot be used "
                              f"with renderer.animate.mode={settings.animate}")
        return settings


def _training_size(tr: ConfigReader) -> dict[str, Any]:
    """``training.width`` and ``training.height``: both ``auto`` or both integers >= 1."""
    raw = {k: tr.get_raw(k, "auto") for k in ("width", "height")}
    autos = [k for k, v in raw.items() if v == "auto"]
    if len(autos) == 2:
        return {"width": None, "height": None}
    if autos:
        raise ConfigError(f"renderer.training.width and height must both be auto or both integers, got "
                          f"width={raw['width']!r} height={raw['height']!r}")
    return {"width": tr.get_int("width", lo=1), "height": tr.get_int("height", lo=1)}


def _unbiased_fraction(tr: ConfigReader) -> float | None:
    """``training.unbiased_fraction``: ``auto`` (None: :func:`auto_unbiased_fraction`) or a number in [0, 1]."""
    return tr.get_float_or_auto("unbiased_fraction", lo=0.0, hi=1.0)


def _carry_frames(tr: ConfigReader) -> int:
    """``training.carry_frames``: an integer >= 0 (``auto``, which carried 4 frames in a thick cloud until
    2026-12-07, is gone: waiting learns faster there, docs/measurements/learning.md, "A frame that waits for its
    training paths")."""
    if tr.get_raw("carry_frames", 0) == "auto":
        raise ConfigError("renderer.training.carry_frames=auto was removed on 2026-12-07 (it carried 4 frames in a "
                          "thick, static cloud of albedo >= 0.99, else 0): give 0 (the default: a frame waits for its "
                          "training paths) or a number of frames")
    return tr.get_int("carry_frames", 0, lo=0)


THICK_OPTICAL_DEPTH = 25.0  # auto: a scene whose median optical depth reaches this is thick (docs/nrc.md, "Learning speed")
UNBIASED_FRACTION = {"static": 1.0, "animated": 1.0}  # auto's values, by whether the camera or light moves: every path
# unbiased in both since 2026-12-07 (a quarter under a moving light left the turning sun 7 % dark with cache.loss's clamp;
# docs/measurements/learning.md, "A loss for unbiased targets" and "A decaying learning rate")
OPTICAL_DEPTH_PIXELS = 64 * 36  # auto: the optical depth is taken over a camera of about this many pixels


def auto_training_regime(scene: Any, animate: str = "none") -> tuple[str, float]:
    """``(regime, median optical depth)``: ``thick`` where the scene's median optical depth over its camera rays
    (:func:`nrc.volume.optical_depth.scene_optical_depth`, on the same camera at about
    :data:`OPTICAL_DEPTH_PIXELS` pixels) reaches :data:`THICK_OPTICAL_DEPTH` and the camera and light are static
    (``animate`` ``none``), else ``moderate``. The ``auto`` settings follow it: the hash table's size
    (:mod:`nrc.cache.encodings.factory`) and the cache's keys that :attr:`CacheGroups.needs_regime` lists
    (:mod:`nrc.cache.settings`)."""
    from nrc.volume.optical_depth import scene_optical_depth

    cam = scene.camera
    k = max(1.0, math.sqrt(cam.num_pixels / OPTICAL_DEPTH_PIXELS))
    small = replace(cam, width=max(1, round(cam.width / k)), height=max(1, round(cam.height / k)))
    tau = scene_optical_depth(replace(scene, camera=small)).median
    return ("thick" if tau >= THICK_OPTICAL_DEPTH and animate == "none" else "moderate"), tau


def auto_unbiased_fraction(animate: str = "none") -> float:
    """``unbiased_fraction: auto``: :data:`UNBIASED_FRACTION` for ``animate`` (``none``: static; else animated). Every
    training path unbiased under a static camera and light, thin or thick (with the loss's floor and clamp,
    ``cache.loss``, unbiased targets learn faster than self-training at optical depth 7 to 196:
    docs/measurements/learning.md, "A loss for unbiased targets"), and under a moving light, where a quarter with
    that loss left the turning sun 7 % dark and all of them were more accurate ("A decaying learning rate"). It does
    not depend on the scene's optical depth."""
    return UNBIASED_FRACTION[_motion(animate)]


def _motion(animate: str) -> str:
    """The key of the ``auto`` tables (:data:`UNBIASED_FRACTION`, :data:`RING_FRAMES`): ``static`` where
    ``animate`` is ``none``, else ``animated``."""
    return "static" if animate == "none" else "animated"


RING_FRAMES = {"static": 4, "animated": 1}  # ring_buffer: auto keeps this many frames of the records a frame leaves,
# by whether the camera or light moves: a moving light's old targets are stale (the turning sun, 3 seeds: 0.083 relMSE
# + OIDN at ~12 frames' records, 0.063 at 4, 0.055 at 1.3; a static cloud's 4 frames no worse than 12, 1 frame 2 %
# darker; docs/measurements/learning.md, "A ring buffer sized to the records a frame leaves")
RING_CAP = 1 << 18  # ... and at most this many


def _ring_buffer(tr: ConfigReader) -> int | None:
    """``training.ring_buffer``: ``auto`` or an integer >= 1."""
    return tr.get_int_or_auto("ring_buffer", "auto", lo=1)


def ring_size(training: TrainingSettings, medium_fraction: float = 1.0, animate: str = "none") -> int:
    """Records the ring buffer keeps: the setting, or (auto) :data:`RING_FRAMES` frames (``animate`` ``none``:
    static; else animated) of the records a frame leaves, at most :data:`RING_CAP`. The training image tiles the
    whole screen and a training path whose camera ray misses the medium leaves no record, so a frame leaves about
    ``n_paths x records_per_path x medium_fraction`` (the fraction of the pixels that see the medium; a third in
    ``scene=thick``): sized to the training image alone, the ring held ~12 frames of records."""
    if training.ring_buffer is not None:
        return training.ring_buffer
    frames = RING_FRAMES[_motion(animate)]
    per_frame = training.n_paths * training.records_per_path * min(max(medium_fraction, 0.0), 1.0)
    return max(1, min(RING_CAP, round(frames * per_frame)))


CHECKPOINT_SECONDS = 60.0  # checkpoint_every: auto writes at least this often while rendering


def _checkpoint_cadence(cfg: ConfigReader) -> dict[str, Any]:
    """``checkpoint_every``: ``auto`` (at the end, on SIGINT/SIGTERM and every 60 s of rendering) or a frame
    count N >= 0 (also every N frames; 0: at the end and on a signal only)."""
    value = cfg.get_raw("checkpoint_every", "auto")
    if value == "auto":
        return {"checkpoint_every": 0, "checkpoint_seconds": CHECKPOINT_SECONDS}
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ConfigError(f"renderer.checkpoint_every must be auto or an integer >= 0, got {value!r}")
    return {"checkpoint_every": value, "checkpoint_seconds": None}


CACHE_GROUPS = ("cache", "encoding", "extra_inputs")  # the radiance cache's config groups (nrc/cache/)


def app_checks(cfg: Any, own_cache: bool = True) -> int:
    """The root-level values ``renderer=nrc`` reads besides ``renderer``: ``frames`` (returned, an int >= 1) and
    the config groups it needs (the cache's only when it builds its own cache)."""
    frames = ConfigReader({"frames": cfg.get("frames", 1)}, "").get_int("frames", lo=1)
    for group in (*(CACHE_GROUPS if own_cache else ()), "batch_filter"):
        if cfg.get(group) is None:
            raise ConfigError(f"renderer=nrc needs the config group '{group}' (see conf/config.yaml)")
    return frames


@dataclass(frozen=True)
class CacheGroups:
    """The radiance cache's config groups (``cache``, ``encoding``, ``extra_inputs``) as plain mappings, validated
    by :func:`nrc.cache.radiance_cache.build_radiance_cache` when the renderer builds its cache."""

    cache: dict[str, Any]
    encoding: dict[str, Any]
    extra_inputs: dict[str, Any]

    @classmethod
    def from_config(cls, cfg: Any) -> CacheGroups:
        from omegaconf import OmegaConf

        def plain(group: str) -> dict[str, Any]:
            block = cfg.get(group)
            return OmegaConf.to_container(block, resolve=True) if OmegaConf.is_config(block) else dict(block)

        return cls(*(plain(g) for g in CACHE_GROUPS))

    @property
    def log2_hashmap_size(self) -> Any:
        """``encoding.position.log2_hashmap_size`` (``auto``: sized by the renderer's training paths)."""
        position = self.encoding.get("position")
        return position.get("log2_hashmap_size") if isinstance(position, dict) else None

    @property
    def needs_regime(self) -> bool:
        """Whether a key of these groups is ``auto`` by the scene's regime (:func:`auto_training_regime`): the hash
        table's ``log2_hashmap_size``, ``cache.loss.clamp_excess``, ``cache.optimizer.lr_hold`` / ``lr_half_life``
        or ``cache.ema.hold_window_fraction``."""
        loss, opt, ema = (self.cache.get(k) for k in ("loss", "optimizer", "ema"))
        return (self.log2_hashmap_size == "auto" or (isinstance(loss, dict) and loss.get("clamp_excess") == "auto")
                or (isinstance(opt, dict) and "auto" in (opt.get("lr_hold"), opt.get("lr_half_life")))
                or (isinstance(ema, dict) and ema.get("hold_window_fraction") == "auto"))


@dataclass(frozen=True)
class NRCRendererSettings:
    """Everything ``renderer=nrc`` reads, typed and validated once (:meth:`from_app_config`), its ``auto`` rules
    resolved for a scene by :func:`resolve_auto` before the renderer is built: one settings object per component,
    passed whole (:class:`nrc.render.radiance_caching.NRCRenderer` takes this, never the raw config)."""

    nrc: NRCSettings  # the ``renderer`` block
    frames: int
    display: Any  # nrc.io.png.DisplaySettings: ``tonemap``, ``exposure`` (the logged images)
    batch_filter: Any  # nrc.render.radiance_caching.batch_filter.BatchFilter (``batch_filter`` group)
    transmittance: Any  # nrc.transport.transmittance.Transmittance (``transmittance`` group)
    cache: CacheGroups | None  # None: no cache groups read (a cache is handed to the renderer)
    config_yaml: str = ""  # the composed config, kept in checkpoints (``renderer.resume`` checks it)
    resolved: bool = False  # the auto rules below and in ``nrc.training`` are resolved (:func:`resolve_auto`)
    optical_depth: float | None = None  # median optical depth over the camera rays, when an auto rule needed it
    regime: str | None = None  # ``thick`` | ``moderate`` (:func:`auto_training_regime`), when an auto rule needed it
    # (H, W) bool, the pixels whose camera ray meets the medium's box: derived from the scene by :func:`resolve_auto`
    # (the training image's size and the renderer's flicker figure read it; computed once, it costs a pass over
    # every pixel)
    medium_mask: Any = field(default=None, repr=False, compare=False)

    @classmethod
    def from_app_config(cls, cfg: Any, own_cache: bool = True) -> NRCRendererSettings:
        """From the app config (``renderer``, ``frames``, ``batch_filter``, ``transmittance``, ``tonemap``,
        ``exposure`` and, with ``own_cache``, ``cache``, ``encoding``, ``extra_inputs``); ``ConfigError`` naming the
        key."""
        from omegaconf import DictConfig, OmegaConf

        from nrc.io.png import DisplaySettings
        from nrc.render.radiance_caching.batch_filter import make_batch_filter
        from nrc.transport.transmittance import make_transmittance

        nrc = NRCSettings.from_config(cfg.renderer)
        frames = app_checks(cfg, own_cache=own_cache)
        return cls(nrc, frames, DisplaySettings.from_config(cfg), make_batch_filter(cfg.batch_filter),
                   make_transmittance(cfg.get("transmittance")), CacheGroups.from_config(cfg) if own_cache else None,
                   OmegaConf.to_yaml(cfg) if isinstance(cfg, DictConfig) else "")

    def resolved_for(self, scene: Any) -> NRCRendererSettings:
        """These settings with their ``auto`` rules resolved for ``scene`` (:func:`resolve_auto`)."""
        return resolve_auto(self, scene)


def resolve_auto(settings: NRCRendererSettings, scene: Any) -> NRCRendererSettings:
    """The ``auto`` rules of ``renderer=nrc`` resolved for ``scene`` (a no-op on resolved settings): the training
    image sized to the pixels that see the medium (:func:`~nrc.render.radiance_caching.training_set.
    auto_training_size`), ``unbiased_fraction`` (:func:`auto_unbiased_fraction`), and, where a key of the renderer's
    own cache is ``auto`` by the regime (:attr:`CacheGroups.needs_regime`), the scene's regime
    (:func:`auto_training_regime`: thick = median optical depth >= :data:`THICK_OPTICAL_DEPTH`, static camera and
    lights) and the values that follow from it."""
    if settings.resolved:
        return settings
    from nrc.render.radiance_caching.training_set import auto_training_size, medium_pixel_mask

    st, tr = settings.nrc, settings.nrc.training
    cam = scene.camera
    mask = medium_pixel_mask(cam, scene.grid)
    if tr.auto:
        w, h = auto_training_size(int(mask.sum()), cam.width, cam.height, tr.paths_per_pixel, tr.min_paths,
                                  tr.max_paths)
        tr = replace(tr, width=w, height=h)
    if tr.unbiased_fraction is None:
        tr = replace(tr, unbiased_fraction=auto_unbiased_fraction(st.animate))
    regime, tau = None, None
    if settings.cache is not None and settings.cache.needs_regime:
        regime, tau = auto_training_regime(scene, st.animate)
    return replace(settings, nrc=replace(st, training=tr), resolved=True, optical_depth=tau,
                   regime=regime, medium_mask=mask)
