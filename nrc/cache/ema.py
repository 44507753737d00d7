"""Exponential moving average of the network weights with start-up debiasing (thesis eq. 4.3).

``ema_k = (alpha mu_{k-1} ema_{k-1} + (1 - alpha) w_k) / mu_k`` with ``mu_k = 1 - alpha^k`` (Adam-style
bias correction; ``ema_1 = w_1``). Since ``alpha mu_{k-1} = mu_k - (1 - alpha)`` this is the update
``ema_k = ema_{k-1} + (1 - alpha) / mu_k * (w_k - ema_{k-1})``, one lerp per parameter and step.
The EMA weights serve inference only; training continues on the raw weights.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn


class WeightEMA:
    """EMA shadow copy of ``model``'s parameters (the cache's buffers are constants, copied once).

    Args:
        model: the trained module (its raw weights).
        alpha: decay in ``[0, 1)``; 0 makes the shadow equal the raw weights.
    """

    def __init__(self, model: nn.Module, alpha: float) -> None:
        self.alpha = alpha
        self.step = 0
        self.model = model
        self.shadow = copy.deepcopy(model).requires_grad_(False).eval()

    @torch.no_grad()
    def update(self) -> None:
        """Fold the current raw weights in as ``w_k`` (call after each optimiser step)."""
        self.step += 1
        rate = (1.0 - self.alpha) / (1.0 - self.alpha**self.step)
        # one call for all parameters (the per-tensor lerp_, batched: the same arithmetic)
        torch._foreach_lerp_(list(self.shadow.parameters()), list(self.model.parameters()), rate)

    def state_dict(self) -> dict[str, Any]:
        return {"step": self.step, "shadow": self.shadow.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = int(state["step"])
        self.shadow.load_state_dict(state["shadow"])
