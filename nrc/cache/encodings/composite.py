"""Composite encoding: consecutive input columns encoded by separate encodings (tcnn ``Composite``)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn


class CompositeEncoding(nn.Module):
    """Split the ``(N, sum n_dims)`` input into column blocks, encode each, concatenate the outputs.

    Args:
        parts: ``(encoding, n_dims)`` pairs in input-column order; each encoding has ``out_dim``.
    """

    def __init__(self, parts: Sequence[tuple[nn.Module, int]]) -> None:
        super().__init__()
        self.encodings = nn.ModuleList(enc for enc, _ in parts)
        self.n_dims = tuple(n for _, n in parts)
        self.in_dim = sum(self.n_dims)
        self.out_dim = sum(int(enc.out_dim) for enc, _ in parts)

    def forward(self, x: Tensor) -> Tensor:
        blocks = torch.split(x, self.n_dims, dim=1)
        return torch.cat([enc(b) for enc, b in zip(self.encodings, blocks)], dim=1)
