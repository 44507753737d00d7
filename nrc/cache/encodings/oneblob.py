"""One-blob encoding (Müller et al. 2019) with tiny-cuda-nn's quartic kernel. tcnn ``{"otype": "OneBlob", "n_bins": k}``.

Each input ``x`` in ``[0, 1]`` is spread over ``k`` bins ``[j/k, (j+1)/k]``: bin ``j`` receives the mass
of the kernel ``K(u) = 15/16 (1 - u^2)^2`` on ``|u| <= 1``, with ``u = (t - x) k`` (radius one bin),
integrated over the bin through its CDF ``C(u) = clamp(15/16 u (1 - 2/3 u^2 + 1/5 u^4) + 1/2, 0, 1)``:
``out_j = C(((j+1)/k - x) k) - C((j/k - x) k)``.

Without wrap-around the bins sum to 1 for ``x`` in ``[1/k, 1 - 1/k]`` (the kernel fits inside
``[0, 1]``) and less near the ends. With wrap-around (periodic inputs, e.g. an azimuth mapped to
``[0, 1)``) the kernel is summed over the shifts ``x - 1, x, x + 1``: bins always sum to 1 and
``x = 0`` and ``x = 1`` encode identically.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn


def quartic_cdf(u: Tensor) -> Tensor:
    """CDF of the quartic kernel ``15/16 (1 - u^2)^2`` on ``[-1, 1]`` (clamped to ``[0, 1]`` outside)."""
    u = u.clamp(-1.0, 1.0)
    u2 = u * u
    return 0.9375 * u * (1.0 - u2 * (2.0 / 3.0) + u2 * u2 * 0.2) + 0.5


class OneBlobEncoding(nn.Module):
    """One-blob encoding of ``n_dims`` inputs in ``[0, 1]``; column ``d * k + j`` is bin ``j`` of dimension ``d``.

    Args:
        n_dims: number of input dimensions.
        n_bins: bins per dimension ``k`` (>= 1).
        wrap: per dimension, whether the input is periodic with period 1 (wrap-around).
    """

    def __init__(self, n_dims: int, n_bins: int, wrap: Sequence[bool]) -> None:
        super().__init__()
        if len(wrap) != n_dims:
            raise ValueError(f"wrap needs {n_dims} flags, got {len(wrap)}")
        self.n_bins = n_bins
        self.wrap = tuple(bool(w) for w in wrap)
        self.out_dim = n_dims * n_bins
        edges = torch.arange(n_bins + 1, dtype=torch.float32) / n_bins
        self.register_buffer("edges", edges, persistent=False)
        self.register_buffer("wrap_mask", torch.tensor(self.wrap)[:, None], persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        k = float(self.n_bins)
        d = (self.edges - x.to(torch.float32)[:, :, None]) * k  # (N, D, k + 1) bin edges relative to x, in bins
        cdf = quartic_cdf(d)
        if any(self.wrap):
            wrapped = cdf + quartic_cdf(d - k) + quartic_cdf(d + k)
            cdf = torch.where(self.wrap_mask, wrapped, cdf)
        return (cdf[..., 1:] - cdf[..., :-1]).reshape(x.shape[0], self.out_dim)
