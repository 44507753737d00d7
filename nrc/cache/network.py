"""The trainable part of the cache: input encodings followed by the MLP."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from nrc.cache.encodings.composite import CompositeEncoding
from nrc.cache.mlp import MLP


class CacheNetwork(nn.Module):
    """Raw inputs ``(N, encoding.in_dim)`` -> RGB radiance ``(N, 3)`` float32.

    Args:
        encoding: composite encoding of the raw input columns.
        width, n_hidden_layers: MLP shape.
        bf16: run the MLP (only) under bfloat16 autocast; encodings and the output stay float32.
        generator: CPU generator for the MLP's initial weights.
    """

    def __init__(self, encoding: CompositeEncoding, width: int, n_hidden_layers: int, bf16: bool,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.encoding = encoding
        self.mlp = MLP(encoding.out_dim, width, n_hidden_layers, 3, generator=generator)
        self.bf16 = bf16

    def forward(self, raw: Tensor) -> Tensor:
        features = self.encoding(raw)
        with torch.autocast(device_type=features.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            rgb = self.mlp(features)
        return rgb.to(torch.float32)
