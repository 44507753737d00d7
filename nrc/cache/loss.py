"""Relative L2 loss on luminance (Müller et al. 2021)."""

from __future__ import annotations

import torch
from torch import Tensor

LUMINANCE_WEIGHTS = (0.299, 0.587, 0.114)
"""Rec. 601 luma weights ``Y = 0.299 r + 0.587 g + 0.114 b``."""


def relative_l2_luminance(prediction: Tensor, target: Tensor, target_clamp: float) -> Tensor:
    """``mean_i sum_c (p_ic - t_ic)^2 / (Y(p_i)^2 + 0.01)``, the denominator detached.

    Args:
        prediction: ``(N, 3)`` predicted linear RGB radiance.
        target: ``(N, 3)`` noisy radiance estimates; clamped to ``[-target_clamp, target_clamp]``
            first (bounds the gradient of fireflies; ``inf`` becomes the clamp value).
        target_clamp: clamp magnitude (> 0), radiance units.

    Returns:
        Scalar loss; exactly 0 (still attached to the graph) for an empty batch.
    """
    if prediction.shape[0] == 0:
        return prediction.sum() * 0.0
    target = target.to(prediction.dtype).clamp(-target_clamp, target_clamp)
    weights = torch.tensor(LUMINANCE_WEIGHTS, dtype=prediction.dtype, device=prediction.device)
    lum = (prediction.detach() * weights).sum(dim=-1, keepdim=True)
    return ((prediction - target).square() / (lum.square() + 0.01)).sum(dim=-1).mean()
