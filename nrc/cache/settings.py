"""Settings of the radiance cache read from the ``cache`` config block (``conf/cache/default.yaml``).

Keys (all validated; unknown keys are errors):

* ``network``: ``n_neurons`` (width, 16..1024; NRC 64/128), ``n_hidden_layers`` (1..16; NRC 3..6),
  ``bf16`` (bfloat16 autocast for the MLP only).
* ``optimizer`` (Adam of the MLP weights): ``lr``, ``beta1``, ``beta2``, ``eps``, ``weight_decay``
  (L2 on MLP weights only); ``lr_final_fraction`` in ``(0, 1]`` or ``auto`` (:data:`LR_FINAL_FRACTION`; absent:
  1) and ``lr_half_life`` (Adam steps, > 0): the MLP's learning rate falls from ``lr`` towards
  ``lr_final_fraction x lr``, halving its distance every ``lr_half_life`` steps (1: constant;
  :meth:`CacheSettings.mlp_lr_factor`), after holding ``lr`` for the first ``lr_hold`` steps (>= 0); either may
  be ``auto``: :data:`LR_SCHEDULE` by the renderer's regime (absent: a half-life of 20 steps, no hold). Hash-grid
  tables take ``lr``/``eps`` from their encoding block, unscheduled.
* ``ema``: ``alpha`` in ``[0, 1)`` (0.99; 0 disables averaging); ``window_fraction`` in ``(0, 1]``: the average
  spans at most about this fraction of the steps so far (1: the plain debiased EMA; :mod:`nrc.cache.ema`);
  ``hold_window_fraction`` in ``(0, 1]`` or ``auto``: the fraction while the MLP's rate is held (the first
  ``optimizer.lr_hold`` steps; :data:`EMA_HOLD_WINDOW` by the regime; absent: ``window_fraction``).
* ``loss``: ``target_clamp`` (> 0, radiance units): targets are clamped to ``[-c, c]``; ``scale_floor`` (>= 0):
  the relative loss's denominator gains ``(f x the batch's mean target luminance)^2`` (0: Müller et al.'s
  ``Y(p)^2 + 0.01``; :func:`nrc.cache.loss.relative_l2_luminance`); ``relative_clamp`` (>= 0, 0: off): a target
  of luminance above ``k x`` the larger of the cache's prediction and the batch's mean is scaled down to it
  (``clamp_to: prediction``; ``mean``: k x the batch's mean alone); ``clamp_excess``: ``drop`` the luminance the
  clamp removes, or ``spread`` it over the batch's targets (the batch's summed target luminance kept), or ``auto``
  (:data:`CLAMP_EXCESS`: drop in a thick cloud, spread otherwise; absent: drop).
* ``query_chunk``: points per forward pass in :meth:`RadianceCache.query` (bounds memory).
* ``compile_training``: ``torch.compile`` the training step's forward, loss and backward (dynamic batch size;
  the fused Adam step is already one kernel). Off by default: on the CPU it measured no faster than eager
  (``docs/measurements/nrc_frames.md``, "Frames bounded by work") and costs a ~30 s compile on a cold cache.
"""

from __future__ import annotations

from dataclasses import dataclass

from nrc.config import ConfigReader
from nrc.cache.optim import AdamSettings


CLAMP_EXCESS = {"thick": "drop", "moderate": "spread"}  # loss.clamp_excess: auto, by the renderer's regime: in a
# thin or moderate cloud (or under a moving camera or light) the relative clamp's lost luminance left the image dark
# (cumulus 9 % after 30 frames, thin back-lit 19 % after 90); spread over the batch both end within 2 % at about
# the same error (the back-lit cloud overshoots first: 5 % bright and 10 % more error after 30 frames); in a thick
# one spreading it cost 7-15 % error and 1-3 % brightness whatever the clamp's factor (the dropped luminance offsets
# a brightness of the thick cache's own; docs/measurements/learning.md, "The clamp's lost luminance")

LR_FINAL_FRACTION = {"static": 0.2, "animated": 1.0}  # optimizer.lr_final_fraction: auto, by whether the camera or
# light moves: a static scene's cache settles at a fifth of the MLP's rate (it drifted bright at the full rate); a moving
# light's keeps the full rate to follow it (docs/measurements/learning.md, "A decaying learning rate")


LR_SCHEDULE = {"thick": (40, 10.0), "moderate": (0, 20.0)}  # (optimizer.lr_hold, lr_half_life) where auto, by the
# renderer's regime: in a thick, static cloud the MLP keeps its full rate for the first 40 Adam steps (10 frames), then
# falls towards its final fraction with a half-life of 10 steps: 8-14 % lower error at frames 10-20 than decaying from
# the start with a half-life of 20, over frames 22-30 within 3 % at optical depth 39 (a constant rate: 13 % worse)
# and 3-5 % lower at 98-196; moderate clouds, not measured with it, decay from step 0 (docs/measurements/learning.md,
# "Holding the MLP's rate")

EMA_HOLD_WINDOW = {"thick": 0.25, "moderate": None}  # ema.hold_window_fraction: auto, by the regime (None: the
# window_fraction): while the MLP's rate is held the EMA averages about the last quarter of the steps, then its window
# grows towards the last half: at frame 10 the image 1-3 % brighter (0.93-1.00 of the reference) and its error 2-8 %
# lower (5 seeds), frames 20-30 within 2 %, frame 3 worse; a quarter throughout lost 7-22 % at frame 30, a sixth during
# the hold cost frame 3 1.3-1.7x for at most 5 % at frame 10 (docs/measurements/learning.md, "A shorter EMA window
# while the rate is held")


@dataclass(frozen=True)
class CacheSettings:
    """Validated contents of the ``cache`` config block (see the module docstring for units and ranges)."""

    n_neurons: int
    n_hidden_layers: int
    bf16: bool
    mlp_adam: AdamSettings
    betas: tuple[float, float]
    ema_alpha: float
    ema_window_fraction: float
    target_clamp: float
    query_chunk: int
    loss_scale_floor: float = 0.0
    loss_relative_clamp: float = 0.0
    loss_clamp_to: str = "prediction"
    loss_clamp_excess: str = "drop"
    compile_training: bool = False
    lr_final_fraction: float = 1.0
    lr_half_life: float = 20.0
    lr_hold: int = 0
    ema_hold_window_fraction: float | None = None

    def mlp_lr_factor(self, step: int) -> float:
        """The MLP's learning rate at Adam step ``step`` (0-based) over ``optimizer.lr``:
        ``F + (1 - F) 2^(-max(0, step - S) / H)``, ``F = lr_final_fraction``, ``H = lr_half_life``, ``S = lr_hold``
        (1 throughout where ``F`` is 1)."""
        if self.lr_final_fraction >= 1.0:
            return 1.0
        decayed = max(0, step - self.lr_hold)
        return self.lr_final_fraction + (1.0 - self.lr_final_fraction) * 0.5 ** (decayed / self.lr_half_life)

    @classmethod
    def from_config(cls, cfg: ConfigReader, animated: bool = False, thick: bool = True) -> CacheSettings:
        """``animated``: whether the renderer's camera or light moves, for ``optimizer.lr_final_fraction: auto``
        (:data:`LR_FINAL_FRACTION`); ``thick``: whether the renderer's regime is thick (a static camera and light,
        median optical depth >= 25), for ``loss.clamp_excess: auto`` (:data:`CLAMP_EXCESS`) and ``optimizer.lr_hold``
        / ``lr_half_life: auto`` (:data:`LR_SCHEDULE`)."""
        net = cfg.block("network")
        opt = cfg.block("optimizer")
        ema = cfg.block("ema")
        loss = cfg.block("loss")
        lr_final = opt.get_float_or_auto("lr_final_fraction", 1.0, lo=0.0, lo_open=True, hi=1.0)
        lr_hold = opt.get_int_or_auto("lr_hold", 0, lo=0)
        half_life = opt.get_float_or_auto("lr_half_life", 20.0, lo=0.0, lo_open=True)
        regime = "thick" if thick else "moderate"
        auto_hold, auto_half_life = LR_SCHEDULE[regime]
        clamp_excess = loss.get_choice("clamp_excess", ["drop", "spread", "auto"], "drop")
        window = ema.get_float("window_fraction", 1.0, lo=0.0, lo_open=True, hi=1.0)
        hold_window = ema.get_float_or_auto("hold_window_fraction", window, lo=0.0, lo_open=True, hi=1.0)
        settings = cls(
            n_neurons=net.get_int("n_neurons", lo=16, hi=1024),
            n_hidden_layers=net.get_int("n_hidden_layers", lo=1, hi=16),
            bf16=net.get_bool("bf16", False),
            mlp_adam=AdamSettings(
                lr=opt.get_float("lr", lo=0.0, lo_open=True),
                eps=opt.get_float("eps", lo=0.0),
                weight_decay=opt.get_float("weight_decay", 0.0, lo=0.0),
            ),
            lr_final_fraction=(LR_FINAL_FRACTION["animated" if animated else "static"] if lr_final is None
                               else lr_final),
            lr_half_life=auto_half_life if half_life is None else half_life,
            lr_hold=auto_hold if lr_hold is None else lr_hold,
            betas=(opt.get_float("beta1", 0.9, lo=0.0, hi=1.0, hi_open=True),
                   opt.get_float("beta2", 0.99, lo=0.0, hi=1.0, hi_open=True)),
            ema_alpha=ema.get_float("alpha", lo=0.0, hi=1.0, hi_open=True),
            ema_window_fraction=window,
            ema_hold_window_fraction=((EMA_HOLD_WINDOW[regime] or window)
                                      if hold_window is None else hold_window),
            target_clamp=loss.get_float("target_clamp", lo=0.0, lo_open=True),
            loss_scale_floor=loss.get_float("scale_floor", 0.0, lo=0.0),
            loss_relative_clamp=loss.get_float("relative_clamp", 0.0, lo=0.0),
            loss_clamp_to=loss.get_choice("clamp_to", ["prediction", "mean"], "prediction"),
            loss_clamp_excess=(CLAMP_EXCESS[regime] if clamp_excess == "auto"
                               else clamp_excess),
            query_chunk=cfg.get_int("query_chunk", 1 << 16, lo=1),
            compile_training=cfg.get_bool("compile_training", False),
        )
        for block in (net, opt, ema, loss, cfg):
            block.finish()
        return settings
