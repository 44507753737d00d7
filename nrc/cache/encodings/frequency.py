"""NeRF frequency (positional) encoding. tcnn ``{"otype": "Frequency", "n_frequencies": L}``."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


class FrequencyEncoding(nn.Module):
    """``sin(2^l pi x)`` and ``cos(2^l pi x)`` for ``l < L``, per input dimension.

    Output ``(N, n_dims * 2 L)``; column ``d * 2L + 2 l`` is the sine and ``d * 2L + 2 l + 1`` the cosine
    of frequency ``l`` of input dimension ``d`` (tiny-cuda-nn's order). Inputs are unitless; the
    lowest frequency has period 2 in ``x``.
    """

    def __init__(self, n_dims: int, n_frequencies: int) -> None:
        super().__init__()
        self.n_frequencies = n_frequencies
        self.out_dim = n_dims * 2 * n_frequencies
        freqs = math.pi * 2.0 ** torch.arange(n_frequencies, dtype=torch.float64)
        self.register_buffer("freqs", freqs.to(torch.float32), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        arg = x.to(torch.float32)[:, :, None] * self.freqs  # (N, D, L)
        return torch.stack((arg.sin(), arg.cos()), dim=-1).reshape(x.shape[0], self.out_dim)
