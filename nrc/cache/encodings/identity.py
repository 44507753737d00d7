"""Identity encoding: passes its inputs through unchanged (as float32)."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class IdentityEncoding(nn.Module):
    """``(N, n_dims)`` -> ``(N, n_dims)``, unchanged. tcnn ``{"otype": "Identity"}``."""

    def __init__(self, n_dims: int) -> None:
        super().__init__()
        self.out_dim = n_dims

    def forward(self, x: Tensor) -> Tensor:
        return x.to(torch.float32)
