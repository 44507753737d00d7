"""Relative L2 loss on luminance (Müller et al. 2021)."""

from __future__ import annotations

import torch
from torch import Tensor

LUMINANCE_WEIGHTS = (0.299, 0.587, 0.114)
"""Rec. 601 luma weights ``Y = 0.299 r + 0.587 g + 0.114 b``."""


def relative_l2_luminance(prediction: Tensor, target: Tensor, target_clamp: float, scale_floor: float = 0.0) -> Tensor:
    """``mean_i sum_c (p_ic - t_ic)^2 / (Y(p_i)^2 + 0.01 + (f |mean_j Y(t_j)|)^2)``, the denominator detached.

    With ``scale_floor`` ``f = 0`` this is Müller et al.'s loss. A floor at a fraction of the batch's mean target
    luminance (the scene's radiance scale, whatever its units) keeps an untrained cache's predictions near 0 from
    weighting every sample 100x (``1 / 0.01``): the relative loss then turns into a plain L2 where predictions are
    below ``f`` times the mean, and stays relative above it (``docs/measurements/learning.md``).

    Args:
        prediction: ``(N, 3)`` predicted linear RGB radiance.
        target: ``(N, 3)`` noisy radiance estimates; clamped to ``[-target_clamp, target_clamp]``
            first (bounds the gradient of fireflies; ``inf`` becomes the clamp value).
        target_clamp: clamp magnitude (> 0), radiance units.
        scale_floor: ``f >= 0``, the denominator's floor as a fraction of the batch's mean target luminance
            (after the clamp).

    Returns:
        Scalar loss; exactly 0 (still attached to the graph) for an empty batch.
    """
    if prediction.shape[0] == 0:
        return prediction.sum() * 0.0
    target = target.to(prediction.dtype).clamp(-target_clamp, target_clamp)
    weights = torch.tensor(LUMINANCE_WEIGHTS, dtype=prediction.dtype, device=prediction.device)
    lum = (prediction.detach() * weights).sum(dim=-1, keepdim=True)
    denominator = lum.square() + 0.01
    if scale_floor > 0.0:
        denominator = denominator + (scale_floor * (target * weights).sum(dim=-1).mean().abs()).square()
    return ((prediction - target).square() / denominator).sum(dim=-1).mean()
