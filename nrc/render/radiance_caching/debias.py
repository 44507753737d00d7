"""Unbiased NRC: the radiance cache as a control variate (``renderer.debias``).

A render path of the NRC renderer stops at a vertex ``x`` (reached along ``d``, throughput ``beta`` before
``x``'s albedo) and adds ``beta C`` with ``C = cache(x, d)``, the quantity the cache stores under
``renderer.cache_target``. Every image is then biased by the cache's error ``L - C``, and accumulating frames
cannot remove it. With ``renderer.debias.probability = q > 0`` the path goes on, with probability ``q``, as a
path-traced suffix that never terminates again, whose contributions ``L_hat`` (an unbiased estimate of exactly
the cached quantity) are weighted ``beta / q``, and the cache's value enters with the weight ``beta (1 - 1/q)``::

    stopped (1 - q):    beta C
    continued (q):      beta C + beta (L_hat - C) / q

The expectation is ``beta E[L_hat]`` for *any* cache, so the frame is an unbiased estimate of the path tracer's
image (the same ``max_scatter``, light sampling and estimators). Both terms use the same ``C``: the cache is
queried once per path, with the weights frozen for the frame (render paths use the EMA weights trained up to the
previous frame), and the one clamp (a negative or non-finite prediction reads 0) applies to both. The
contributions of continued paths can be negative (``C`` above the suffix's estimate): they are never clamped in
the image, whose pixels may be negative; only the denoiser's copy is clamped (:mod:`nrc.denoise`), and the
metrics report the bias that clamp adds (``denoise_clamp_bias``).

With ``cache_target: indirect`` the terminal vertex keeps its own next-event estimate (light sampling alone,
throughput ``beta``, outside the ``1/q``) and ``L_hat`` is the suffix's indirect light: the environment that the
continued path's first phase-sampled direction reaches is not counted (it is direct light, which the vertex's
estimate already covers). With ``full`` the continued vertex does the path tracer's next-event estimate with MIS,
all of it inside the ``1/q``.

**Variance** at the vertex: ``beta^2 (E[(L_hat - C)^2] / q - (L - C)^2)`` added to the variance of the biased
estimator's terms. The cache removes the variance of where the vertex lands, not the suffix's own noise
(``E[(L_hat - C)^2] >= Var(L_hat)``): the gain over the path tracer is the suffix cost saved when ``1 - q`` of
the paths stop, paid for by ``1/q`` times the suffix's variance and by the cache's inference and training.
Per frame the renderer measures the correction's second moment per render sample, ``M = q E[c^2]`` with
``c = beta (L_hat - C) / q`` over the continued samples (``debias_correction_moment``; the variance the
correction adds to a sample is about ``M / q``), and the cache's error where render paths terminate,
``E[beta (L_hat - C)] / E[beta C]`` (``debias_cache_error``: the relative bias the biased renderer would have
there, measured online).

**Suffixes as training data** (``train_on_suffixes``): a continued suffix is an unbiased estimate of the cached
quantity at ``(x, d)``; its record ``(x, d) -> suffix q / beta`` is pushed into the ring buffer, from which the
training batches' invalid records are filled.

========================== ======= =================================================================
``renderer.debias`` key    default meaning
========================== ======= =================================================================
``probability``            0.0     ``q``: probability that a render path goes on past its cache termination
                                   (0: the biased NRC of Müller et al.; 1: the path tracer's estimator,
                                   the cache cancels). Changing it recompiles nothing (it travels in ``P``);
                                   0 and > 0 are different step structures.
``train_on_suffixes``      true    push the continued suffixes into the ring buffer as training records
========================== ======= =================================================================

Memory: one suffix row (3 floats) per render sample of a frame, and per continued path its sample id and
throughput.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.radiance_caching.ring_buffer import TrainingRecords
from nrc.transport.light_sampling import luminance3


@dataclass(frozen=True)
class DebiasSettings:
    """``renderer.debias`` (``conf/renderer/nrc.yaml``; the module docstring has the table)."""

    probability: float = 0.0
    """``q`` in ``[0, 1]``: a render path that would terminate into the cache goes on with this probability."""
    train_on_suffixes: bool = True
    """The continued suffixes enter the ring buffer as training records."""

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
