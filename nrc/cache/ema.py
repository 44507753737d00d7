"""Exponential moving average of the network weights with start-up debiasing (thesis eq. 4.3).

``ema_k = (alpha mu_{k-1} ema_{k-1} + (1 - alpha) w_k) / mu_k`` with ``mu_k = 1 - alpha^k`` (Adam-style
bias correction; ``ema_1 = w_1``). Since ``alpha mu_{k-1} = mu_k - (1 - alpha)`` this is the update
``ema_k = ema_{k-1} + (1 - alpha) / mu_k * (w_k - ema_{k-1})``, one lerp per parameter and step.
The EMA weights serve inference only; training continues on the raw weights.

Early on the debiased rate is about ``1/k``: a plain average of *every* step so far, the first (untrained) ones
included, which keeps a young cache dark and late. ``window_fraction`` f < 1 bounds the average to about the last
``f k`` steps: the rate is ``max((1 - alpha) / mu_k, 1 / (1 + f (k - 1)))``, so the window grows with the cache's
age until it reaches the EMA's own ``1 / (1 - alpha)`` steps (at ``k ~ 1 / (f (1 - alpha))``), after which the
update is the plain one. f = 1 is the debiased EMA exactly (``(1 - alpha) / mu_k >= 1 / k`` always).

While the MLP's learning rate is held at its full value (``cache.optimizer.lr_hold``: the raw weights move fastest)
the window may be shorter: ``hold_fraction`` replaces f for the first ``hold`` steps; the window then grows from
``hold_fraction k`` towards ``f k`` as new steps come in (the lerp's state is kept, only its rate changes).
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
        window_fraction: in ``(0, 1]``: the average spans at most about this fraction of the steps so far
            (1: the debiased EMA).
        hold: steps (from the first) whose window fraction is ``hold_fraction`` (the MLP rate's hold).
        hold_fraction: in ``(0, 1]``, the window fraction of the first ``hold`` steps (None: ``window_fraction``).
    """

    def __init__(self, model: nn.Module, alpha: float, window_fraction: float = 1.0, hold: int = 0,
                 hold_fraction: float | None = None) -> None:
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"EMA alpha must be in [0, 1), got {alpha}")
        for name, f in (("window_fraction", window_fraction), ("hold_window_fraction", hold_fraction)):
            if f is not None and not 0.0 < f <= 1.0:
                raise ValueError(f"EMA {name} must be in (0, 1], got {f}")
        self.alpha = alpha
        self.window_fraction = window_fraction
        self.hold = hold
        self.hold_fraction = window_fraction if hold_fraction is None else hold_fraction
        self.step = 0
        self.model = model
        self.shadow = copy.deepcopy(model).requires_grad_(False).eval()

    @torch.no_grad()
    def update(self) -> None:
        """Fold the current raw weights in as ``w_k`` (call after each optimiser step)."""
        self.step += 1
        rate = self.rate(self.step)
        # one call for all parameters (the per-tensor lerp_, batched: the same arithmetic)
        torch._foreach_lerp_(list(self.shadow.parameters()), list(self.model.parameters()), rate)

    def rate(self, k: int) -> float:
        """The lerp rate of step ``k`` (from 1): the debiased rate, or the age-bounded window's where larger."""
        debiased = (1.0 - self.alpha) / (1.0 - self.alpha**k)
        f = self.hold_fraction if k <= self.hold else self.window_fraction
        return max(debiased, 1.0 / (1.0 + f * (k - 1)))

    def state_dict(self) -> dict[str, Any]:
        return {"step": self.step, "shadow": self.shadow.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = int(state["step"])
        self.shadow.load_state_dict(state["shadow"])
