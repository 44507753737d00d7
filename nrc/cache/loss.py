"""Relative L2 loss on luminance (Müller et al. 2021)."""

from __future__ import annotations

import torch
from torch import Tensor

LUMINANCE_WEIGHTS = (0.299, 0.587, 0.114)
"""Rec. 601 luma weights ``Y = 0.299 r + 0.587 g + 0.114 b``."""


def relative_l2_luminance(prediction: Tensor, target: Tensor, target_clamp: float, scale_floor: float = 0.0,
                          relative_clamp: float = 0.0, clamp_to: str = "prediction",
                          clamp_excess: str = "drop") -> Tensor:
    """``mean_i sum_c (p_ic - t_ic)^2 / (Y(p_i)^2 + 0.01 + (f m)^2)``, the denominator detached, ``m`` the batch's
    mean target luminance ``|mean_j Y(t_j)|`` (after ``target_clamp``).

    With ``scale_floor`` ``f = 0`` this is Müller et al.'s loss. A floor at a fraction of the batch's mean target
    luminance (the scene's radiance scale, whatever its units) keeps an untrained cache's predictions near 0 from
    weighting every sample 100x (``1 / 0.01``): the relative loss then turns into a plain L2 where predictions are
    below ``f`` times the mean, and stays relative above it (``docs/measurements/learning.md``).

    Args:
        prediction: ``(N, 3)`` predicted linear RGB radiance.
        target: ``(N, 3)`` noisy radiance estimates; clamped to ``[-target_clamp, target_clamp]``
            first (bounds the gradient of fireflies; ``inf`` becomes the clamp value).
        target_clamp: clamp magnitude (> 0), radiance units.
        scale_floor: ``f >= 0``, the denominator's floor as a fraction of ``m``.
        relative_clamp: ``k >= 0`` (0: off): a target whose luminance exceeds ``k max(Y(p_i), m)`` is scaled down to
            it (its colour kept): bounded by the cache's own prediction where it has learned more than the batch's
            mean, by the mean where it has not. A biased (darkening) bound on the rare paths that carry many times
            what the cache predicts; Adam turns their large gradients into lasting upward steps, which left the
            image brighter than the reference with unbiased targets (``docs/measurements/learning.md``).
        clamp_to: ``prediction`` (the above) or ``mean``: the cap is ``k m`` for every target (measured: it darkens
            back-lit scenes, whose bright targets are real).
        clamp_excess: ``drop`` (the clamped luminance is lost) or ``spread``: the luminance the clamp removed is given
            back to the batch, every target of positive luminance scaled by ``1 + removed / kept`` (``kept`` their
            clamped luminance's sum), so the batch's summed target luminance is what it was before the clamp. The
            rare bright paths still take no large step of their own, and a cache whose prediction is low no longer
            settles below the mean (the prediction-relative cap ratchets down with it otherwise).

    Returns:
        Scalar loss; exactly 0 (still attached to the graph) for an empty batch.
    """
    if prediction.shape[0] == 0:
        return prediction.sum() * 0.0
    target = target.to(prediction.dtype).clamp(-target_clamp, target_clamp)
    weights = torch.tensor(LUMINANCE_WEIGHTS, dtype=prediction.dtype, device=prediction.device)
    lum = (prediction.detach() * weights).sum(dim=-1, keepdim=True)
    denominator = lum.square() + 0.01
    if scale_floor > 0.0 or relative_clamp > 0.0:
        target_lum = (target * weights).sum(dim=-1, keepdim=True)
        mean = target_lum.mean().abs()
        if relative_clamp > 0.0:
            cap = relative_clamp * (torch.maximum(lum, mean) if clamp_to == "prediction" else mean)
            scale = torch.where(target_lum > cap, cap / target_lum, torch.ones_like(target_lum))
            target = target * scale
            if clamp_excess == "spread":
                positive = target_lum > 0.0
                removed = (target_lum * (1.0 - scale)).sum()
                kept = torch.where(positive, target_lum * scale, torch.zeros_like(target_lum)).sum()
                gain = 1.0 + removed / kept.clamp_min(torch.finfo(kept.dtype).tiny)
                target = target * torch.where(positive, gain, torch.ones_like(gain))
        denominator = denominator + (scale_floor * mean).square()
    return ((prediction - target).square() / denominator).sum(dim=-1).mean()
