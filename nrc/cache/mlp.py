"""Fully connected network of the radiance cache (tiny-cuda-nn ``FullyFusedMLP`` layout)."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


class MLP(nn.Module):
    """``n_hidden_layers`` hidden layers of ``width`` ReLU neurons, no bias vectors, linear RGB output.

    There are ``n_hidden_layers + 1`` weight matrices: ``in_dim -> width``, ``width -> width`` (repeated)
    and ``width -> out_dim``. Hidden weights are He-uniform (``U(-sqrt(6/fan_in), +)``), the output
    layer Xavier-uniform; drawn from ``generator`` for reproducibility.
    """

    def __init__(self, in_dim: int, width: int, n_hidden_layers: int, out_dim: int = 3,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        dims = [in_dim] + [width] * n_hidden_layers + [out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b, bias=False) for a, b in zip(dims[:-1], dims[1:]))
        with torch.no_grad():
            for i, layer in enumerate(self.layers):
                fan_out, fan_in = layer.weight.shape
                last = i == len(self.layers) - 1
                bound = math.sqrt(6.0 / (fan_in + fan_out)) if last else math.sqrt(6.0 / fan_in)
                layer.weight.uniform_(-bound, bound, generator=generator)

    def forward(self, x: Tensor) -> Tensor:
        for layer in self.layers[:-1]:
            x = torch.relu_(layer(x))  # in place: the matmul's backward does not need its own output
        return self.layers[-1](x)
