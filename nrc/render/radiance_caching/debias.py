"""Unbiased NRC: the radiance cache as a control variate (``renderer.debias``).

A render path that would stop at a vertex ``x`` (along ``d``, throughput ``beta``) and add ``beta C``,
``C = cache(x, d)``, goes on with probability ``q`` as a path-traced suffix that never terminates again, whose
contributions ``L_hat`` are weighted ``beta / q``, while the cache enters with the weight ``beta (1 - 1/q)``::

    stopped (1 - q):    beta C
    continued (q):      beta C + beta (L_hat - C) / q

The expectation is ``beta E[L_hat]`` for any cache: every frame is an unbiased estimate of the path tracer's
image. Here: the settings (:class:`DebiasSettings`), the estimator's per-frame statistics and the suffixes' training
records; the draw is in NRC's vertex program (:mod:`nrc.render.radiance_caching.vertex`). The derivation, the
``cache_target`` cases, the variance, the tests and the measurements: ``docs/nrc.md``, "Unbiased NRC".

Memory: one suffix row (3 floats) per render sample of a frame, and per continued path its sample id and
throughput.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.radiance_caching.ring_buffer import TrainingRecords
from nrc.transport.lights import luminance3


@dataclass(frozen=True)
class DebiasSettings:
    """``renderer.debias`` (``conf/renderer/nrc.yaml``)."""

    probability: float = 0.0
    """``q`` in ``[0, 1]``: a render path that would terminate into the cache goes on with this probability (0: the
    biased NRC of Müller et al.; 1: the path tracer's estimator, the cache cancels). Changing it recompiles nothing
    (it travels in ``P``); 0 and > 0 are different step structures."""
    train_on_suffixes: bool = True
    """The continued suffixes enter the ring buffer as training records ``(x, d) -> suffix q / beta`` (an unbiased
    estimate of the cached quantity), from which the training batches' invalid records are filled."""

    @classmethod
    def from_config(cls, cfg: Any) -> DebiasSettings:
        """Read the ``debias`` block of a :class:`nrc.config.ConfigReader` of the ``renderer`` block (missing keys
        take the defaults)."""
        d = cls()
        r = cfg.block("debias")
        settings = cls(probability=r.get_float("probability", d.probability, lo=0.0, hi=1.0),
                       train_on_suffixes=r.get_bool("train_on_suffixes", d.train_on_suffixes))
        r.finish()
        return settings

    @property
    def enabled(self) -> bool:
        return self.probability > 0.0

    def metrics(self) -> dict[str, Any]:
        return {"debias_probability": self.probability,
                "debias_train_on_suffixes": self.train_on_suffixes if self.enabled else None}


def _luminance(rgb: Tensor) -> Tensor:
    """Luminance ``(N,)`` of ``(N, 3)`` linear RGB."""
    return luminance3(rgb.unbind(-1))


def apply(trace: Any, values: Tensor, spp: int, q: float) -> dict[str, Any]:
    """Add the continued render paths' suffix rows of ``trace`` (a :class:`~nrc.render.radiance_caching.paths.
    FrameTrace`) to its pixels and return the frame's debiasing statistics; ``values`` ``(Q, 3)`` are the cache
    values of the trace's queries (as clamped for the image)."""
    acc, suffix = trace.acc, trace.suffix
    n_render = suffix.shape[0]
    pix = torch.div(torch.arange(n_render, device=acc.device), spp, rounding_mode="floor")
    acc[:trace.n_pixels].index_add_(0, pix, suffix)
    cont = trace.query_cont
    C = values[cont]
    corr = suffix[trace.cont_pid] - trace.cont_beta / q * C  # beta (L_hat - C) / q of each continued path
    render = trace.query_pid < n_render
    stopped = render & ~cont
    cached = _luminance(trace.query_w[stopped] * values[stopped]).sum() + _luminance(trace.cont_beta * C).sum()
    lum = _luminance(corr)
    n = max(n_render, 1)
    return {
        "debias_q": q,
        "debias_terminations": int(render.sum()),
        "debias_continued": int(cont.sum()),
        "debias_correction_moment": float(q * (lum * lum).sum() / n),
        "debias_cache_error": float(lum.sum() / cached) if float(cached) > 0 else None,
    }


def suffix_records(trace: Any, q: float) -> tuple[TrainingRecords, Tensor]:
    """Training records of the continued suffixes: ``(x, d) -> suffix q / beta`` (an unbiased estimate of the
    cached quantity at the continued vertex) and their validity (finite, positive throughput)."""
    cont = trace.query_cont
    beta = trace.cont_beta
    target = trace.suffix[trace.cont_pid] * q / beta.clamp(min=1e-30)
    valid = (beta > 0).all(dim=1) & torch.isfinite(target).all(dim=1)
    target = torch.where(valid[:, None], target, torch.zeros_like(target))
    return TrainingRecords(trace.query_x[cont], trace.query_d[cont], target), valid
