"""Triangle-wave encoding of NRC (Müller et al. 2021). tcnn ``{"otype": "TriangleWave", "n_frequencies": L}``.

For frequency ``f < L``: ``v = x 2^f / 2 + f / 4`` and ``out = 4 |v - floor(v) - 1/2| - 1`` in ``[-1, 1]``
(tiny-cuda-nn's convention; the ``f / 4`` phase shift disambiguates locations).

Relation to the frequency encoding: ``4 |v - floor(v) - 1/2| - 1`` is the triangle wave that matches
``cos(2 pi v)`` at its extrema and zeros, so level ``f`` approximates
``cos(2^f pi x + f pi / 2) = sin(2^f pi x + (f + 1) pi / 2)``, i.e. the frequency encoding's sine of the
same frequency at the shifted input ``x + (f + 1) / 2^(f+1)`` (no shift needed when ``f = 3 mod 4``).
The largest difference ``max_v |tri(v) - cos(2 pi v)|`` is reached where ``sin(2 pi v) = 2 / pi``:
``sqrt(1 - 4/pi^2) - 1 + 2 asin(2/pi) / pi = 0.2105`` (see ``MAX_ERROR_VS_SINE``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

MAX_ERROR_VS_SINE = math.sqrt(1.0 - 4.0 / math.pi**2) - 1.0 + 2.0 * math.asin(2.0 / math.pi) / math.pi
"""``max |triangle level f(x) - sin(2^f pi x + (f + 1) pi / 2)|`` over all ``x`` (about 0.2105)."""


class TriangleWaveEncoding(nn.Module):
    """Triangle waves of ``L`` octaves per input dimension; column ``d * L + f``. Output ``(N, n_dims * L)``."""

    def __init__(self, n_dims: int, n_frequencies: int) -> None:
        super().__init__()
        self.n_frequencies = n_frequencies
        self.out_dim = n_dims * n_frequencies
        f = torch.arange(n_frequencies, dtype=torch.float32)
        self.register_buffer("scale", 2.0**f / 2.0, persistent=False)
        self.register_buffer("phase", 0.25 * f, persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        v = torch.addcmul(self.phase, x.to(torch.float32)[:, :, None], self.scale)  # (N, D, L)
        out = (v - v.floor() - 0.5).abs_().mul_(4.0).sub_(1.0)
        return out.reshape(x.shape[0], self.out_dim)
