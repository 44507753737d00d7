"""Fully connected network of the radiance cache (tiny-cuda-nn ``FullyFusedMLP`` layout)."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


class MLP(nn.Module):
    """``n_hidden_layers`` hidden layers of ``width`` ReLU neurons, no bias vectors, linear RGB output.

    There are ``n_hidden_layers + 1`` weight matrices: ``in_dim -> width``, ``width -> width`` (repeated)
    and ``width -> out_dim``. Hidden weights are He-uniform (``U(-sqrt(6/fan_in), +)``), drawn from
    ``generator`` for reproducibility; the output layer starts at zero, so an untrained cache predicts
    0. A random output layer would not: behind ReLUs the features are non-negative, so each output
    channel starts with its own random offset (measured: ~+0.3 red, negative green), and in online
    self-training that offset enters the targets through the cached terminal values and decays only
    by the fraction of light that escapes in ``extra_vertices`` bounces — a thick albedo-1 cloud stayed
    visibly pink for 40 frames.
    """

    def __init__(self, in_dim: int, width: int, n_hidden_layers: int, out_dim: int = 3,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        dims = [in_dim] + [width] * n_hidden_layers + [out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b, bias=False) for a, b in zip(dims[:-1], dims[1:]))
        with torch.no_grad():
            for layer in self.layers[:-1]:
                layer.weight.uniform_(-math.sqrt(6.0 / layer.weight.shape[1]), math.sqrt(6.0 / layer.weight.shape[1]),
                                      generator=generator)
            self.layers[-1].weight.zero_()

    def forward(self, x: Tensor) -> Tensor:
        for layer in self.layers[:-1]:
            x = torch.relu_(layer(x))  # in place: the matmul's backward does not need its own output
        return self.layers[-1](x)
