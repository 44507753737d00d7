"""Adam parameter groups of the cache: network weights and parametric encodings (hash grids).

Conventions (tiny-cuda-nn / Müller 2021): Adam with betas ``(0.9, 0.99)``; hash tables use
``eps = 1e-15`` and their own learning rate (1e-2 by default); the L2 penalty (Adam ``weight_decay``,
i.e. ``wd * w`` added to the gradient) applies to the MLP weights only.

Dense and lazy updates of a hash table: tiny-cuda-nn's Adam skips the table entries whose gradient is exactly 0 (no
moment decay, no update, a step count per entry). ``torch.optim.Adam`` updates every entry each step, so the momentum
of an entry no batch touched keeps moving it. An encoding block's ``lazy: true`` gives its table the
tiny-cuda-nn update (:class:`LazyAdam`: per table row, a row being all features of one grid vertex); ``false`` the
dense one. The defaults (hash-table lr, the EMA) were measured with the update each names
(docs/measurements/learning.md).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class AdamSettings:
    """Adam hyper-parameters of one parameter group (``lr`` per step, ``weight_decay`` = L2 factor)."""

    lr: float
    eps: float
    weight_decay: float = 0.0
    lazy: bool = False  # entries with a zero gradient keep their moments (:class:`LazyAdam`; 2-D ``(F, R)`` tables)


class LazyAdam(torch.optim.Optimizer):
    """Adam that updates only the columns of a ``(F, R)`` table with a nonzero gradient (tiny-cuda-nn's rule).

    A column is one table row (a grid vertex's ``F`` features). Each column has its own step count, so a column's
    bias correction counts the steps that touched it; columns no batch touched keep their moments and values.
    No weight decay (the tables take none). Memory: two ``(F, R)`` moments and an ``(R,)`` int32 step count.
    """

    def __init__(self, params: Iterable[nn.Parameter], lr: float, betas: tuple[float, float], eps: float) -> None:
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps, "weight_decay": 0.0})
        for group in self.param_groups:
            for p in group["params"]:
                if p.dim() != 2:
                    raise ValueError(f"LazyAdam updates (F, R) tables by column, got a {p.dim()}-D parameter")

    @torch.no_grad()
    def step(self, closure: None = None) -> None:  # type: ignore[override]
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros(p.shape[1], dtype=torch.int32, device=p.device)
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                cols = p.grad.ne(0).any(dim=0).nonzero().squeeze(1)
                if cols.numel() == 0:
                    continue
                g = p.grad.index_select(1, cols)
                t = state["step"].index_select(0, cols) + 1
                state["step"].index_copy_(0, cols, t)
                m = state["exp_avg"].index_select(1, cols).mul_(b1).add_(g, alpha=1.0 - b1)
                v = state["exp_avg_sq"].index_select(1, cols).mul_(b2).addcmul_(g, g, value=1.0 - b2)
                state["exp_avg"].index_copy_(1, cols, m)
                state["exp_avg_sq"].index_copy_(1, cols, v)
                tf = t.to(p.dtype)
                bc1, bc2 = 1.0 - b1**tf, 1.0 - b2**tf
                update = (m / bc1).div_((v / bc2).sqrt_().add_(group["eps"])).mul_(group["lr"])
                p.index_add_(1, cols, update, alpha=-1.0)  # cols are unique: p[:, cols] -= update


class CacheOptimizer:
    """The cache's optimisers as one: a fused Adam over the dense groups and a :class:`LazyAdam` per lazy one.

    ``param_groups`` lists every group (the dense ones first, in their order); ``state_dict`` holds each
    optimiser's state."""

    def __init__(self, optimizers: list[torch.optim.Optimizer]) -> None:
        self.optimizers = optimizers

    @property
    def param_groups(self) -> list[dict]:
        return [g for o in self.optimizers for g in o.param_groups]

    def zero_grad(self, set_to_none: bool = True) -> None:
        for o in self.optimizers:
            o.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        for o in self.optimizers:
            o.step()

    def state_dict(self) -> dict:
        return {"optimizers": [o.state_dict() for o in self.optimizers]}

    def load_state_dict(self, state: dict) -> None:
        if len(state.get("optimizers", ())) != len(self.optimizers):
            raise ValueError("the checkpoint's optimiser state does not match this cache's (dense / lazy groups)")
        for o, s in zip(self.optimizers, state["optimizers"]):
            o.load_state_dict(s)


def build_adam(
    groups: Iterable[tuple[nn.Module, AdamSettings]], betas: tuple[float, float]
) -> torch.optim.Adam | CacheOptimizer:
    """One Adam over the parameters of each module, with that module's settings as a parameter group; a
    :class:`CacheOptimizer` when a group is lazy (its module's parameters then get a :class:`LazyAdam`).

    The dense groups use the fused (single-kernel) implementation: on CPU it is ~4x faster than the per-tensor
    loop for hash tables of millions of entries.
    """
    param_groups, lazy = [], []
    for module, s in groups:
        params = [p for p in module.parameters() if p.requires_grad]
        if params and s.lazy:
            lazy.append(LazyAdam(params, s.lr, betas, s.eps))
        elif params:
            param_groups.append({"params": params, "lr": s.lr, "eps": s.eps, "weight_decay": s.weight_decay})
    dense = torch.optim.Adam(param_groups, betas=betas, fused=True)
    return CacheOptimizer([dense, *lazy]) if lazy else dense
