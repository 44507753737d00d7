"""Multiresolution hash encoding (Müller et al. 2022, instant-NGP) with tiny-cuda-nn conventions.

Input: positions ``(N, 3)`` in ``[0, 1]^3`` (values outside are clamped). Output ``(N, L * F)``,
level-major: ``[level 0 features, level 1 features, ...]``.

Conventions (those of tiny-cuda-nn's ``HashGrid``):

* Level ``l`` has ``scale_l = N_min * b^l - 1`` with per-level scale ``b``; a position ``x`` maps to
  the continuous grid coordinate ``x * scale_l + 0.5`` (the half-cell offset staggers the levels).
* The level's resolution is ``res_l = ceil(scale_l) + 1``; the offset makes vertex coordinates
  ``0 .. res_l`` reachable, i.e. ``res_l + 1`` vertices per axis.
* A level is *dense* when ``(res_l + 1)^3 <= T`` and then indexes its vertices as
  ``i + j (res_l + 1) + k (res_l + 1)^2``; otherwise it is *hashed*:
  ``(i * 1  XOR  j * 2654435761  XOR  k * 805459861) mod T`` in uint32 arithmetic. The products are
  taken in int64 and masked with ``T - 1``: since ``T`` is a power of two dividing ``2^32``, this
  equals the uint32 wrap-around followed by ``mod T`` bit for bit.
* Features are trilinearly interpolated between the 8 cell corners, initialised ``U(-1e-4, 1e-4)``
  and trained. One ``(F, R)`` parameter holds every level's rows back to back: ``(res_l + 1)^3`` rows
  for a dense level, ``T`` for a hashed one (as tiny-cuda-nn sizes them), so coarse levels cost no
  optimiser, EMA or gradient work for rows they can never index.

Performance (CPU; measured with 2^16 points, one thread). All levels are processed at once with the
``N`` points innermost in every tensor (an inner dimension of 2 or 8 makes element-wise ops several
times slower): per-axis index terms ``(L, 3, 2, N)`` in int64, combined into ``(L, 8, N)`` int32
corner rows by two adds/XORs; per feature one ``index_select`` gathers all 8 corners x L levels and
a multiply-sum interpolates. The backward is an ``index_add_`` scatter of the weighted output
gradient. Alternatives measured (L = 16, gather + scatter, forward + backward): ``embedding_bag``
with ``per_sample_weights`` ~1.1 s (its built-in backward is the bottleneck) vs ~0.18 s here; plain
autograd through ``index_select`` does the same ``index_add_`` but receives the output gradient as a
transposed, strided view, which made the training step of a 16-level cache 3x slower, hence the
custom autograd function that makes it contiguous first.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

PRIMES = (1, 2654435761, 805459861)
"""Spatial hash primes for x, y, z (tiny-cuda-nn's ``fast_hash``)."""


class _Interpolate(torch.autograd.Function):
    """``out[f, l, n] = sum_c w[l, c, n] * table[f, idx[l, c, n]]`` with a scatter-add backward.

    Shapes: ``table (F, R)``, ``idx (L, 8, N)`` int32 rows of ``table[f]`` (each level's offset
    included), ``w (L, 8, N)``; output ``(F, L, N)``. Every tensor keeps the
    ``N`` points innermost, so all element-wise work runs on long contiguous rows (on CPU, an inner
    dimension of 2 or 8 is several times slower).
    """

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, w: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(idx, w)
        ctx.table_shape = table.shape
        flat_idx = idx.view(-1)
        out = []
        for rows in table.detach():
            corner = rows.index_select(0, flat_idx).view(idx.shape)
            out.append(corner.mul_(w).sum(dim=1))
        return torch.stack(out)

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, None, None]:  # type: ignore[override]
        idx, w = ctx.saved_tensors
        grad = torch.zeros(ctx.table_shape, dtype=w.dtype, device=w.device)
        # scatter_add_ adds in the same order as index_add_ (bitwise the same table gradient) and on the CPU takes
        # ~0.6x its time at a training batch (it wants int64 rows: one conversion serves every feature).
        flat_idx = idx.view(-1).long()
        # grad_out arrives as a transposed view of the (N, L * F) output gradient: make N innermost.
        for rows, g in zip(grad, grad_out.contiguous()):
            rows.scatter_add_(0, flat_idx, (g[:, None, :] * w).view(-1))
        return grad, None, None


class HashGridEncoding(nn.Module):
    """Trainable multiresolution hash grid over ``[0, 1]^3``.

    Args:
        n_levels: number of levels ``L`` (>= 1).
        n_features_per_level: features per level ``F`` (>= 1).
        log2_hashmap_size: ``log2 T``, table rows per level (``L * T < 2^31``).
        base_resolution: ``N_min`` (>= 1).
        per_level_scale: ``b`` (>= 1); the finest level has ``N_max = N_min b^(L-1)``.
        generator: CPU random generator for the initial features (seeded runs are reproducible).

    Attributes:
        table: ``(F, R)`` trainable features; feature ``f`` of row ``r`` of level ``l`` is
            ``table[f, level_offsets[l] + r]`` (see :meth:`level_table`).
        resolutions: ``res_l = ceil(scale_l) + 1`` per level (``res_l + 1`` vertices per axis).
        dense: per level, whether it is indexed densely (dense levels come first).
    """

    def __init__(
        self,
        n_levels: int,
        n_features_per_level: int,
        log2_hashmap_size: int,
        base_resolution: int,
        per_level_scale: float,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.n_levels = n_levels
        self.n_features_per_level = n_features_per_level
        self.hashmap_size = 1 << log2_hashmap_size
        self.out_dim = n_levels * n_features_per_level
        t = self.hashmap_size
        scales = torch.tensor(
            [base_resolution * per_level_scale**level - 1.0 for level in range(n_levels)], dtype=torch.float32
        )
        self.resolutions = tuple(math.ceil(float(s)) + 1 for s in scales)
        self.dense = tuple((r + 1) ** 3 <= t for r in self.resolutions)
        self.n_dense_levels = sum(self.dense)
        sizes = [(r + 1) ** 3 if d else t for r, d in zip(self.resolutions, self.dense)]
        self.level_sizes = tuple(sizes)
        self.level_offsets = tuple(sum(sizes[:level]) for level in range(n_levels))
        mult = [[1, r + 1, (r + 1) ** 2] if d else list(PRIMES) for r, d in zip(self.resolutions, self.dense)]
        self.register_buffer("scales", scales, persistent=False)
        self.register_buffer("_mult", torch.tensor(mult, dtype=torch.int64)[:, :, None], persistent=False)
        self.register_buffer(
            "_level_offset", torch.tensor(self.level_offsets, dtype=torch.int32)[:, None, None], persistent=False
        )
        table = torch.empty(n_features_per_level, sum(sizes)).uniform_(-1e-4, 1e-4, generator=generator)
        self.table = nn.Parameter(table)

    def level_table(self, level: int) -> Tensor:
        """The ``(F, rows)`` view of ``table`` holding level ``level``'s rows."""
        start = self.level_offsets[level]
        return self.table[:, start:start + self.level_sizes[level]]

    def corners(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Table rows and trilinear weights of the 8 cell corners of every point at every level.

        Args:
            x: ``(N, 3)`` positions in ``[0, 1]^3`` (clamped).

        Returns:
            ``(idx, w)``, each ``(L, 8, N)``: ``idx`` int32 rows of ``table[f]`` (level offset included), ``w`` float32 weights; corner ``c = 4 i + 2 j + k`` is the vertex
            ``(floor(u) + i, floor(v) + j, floor(w) + k)`` of the grid coordinate ``(u, v, w)``.
        """
        n, n_levels, mask = x.shape[0], self.n_levels, self.hashmap_size - 1
        xt = x.detach().to(torch.float32).clamp(0.0, 1.0).t()
        pos = torch.addcmul(torch.full((), 0.5, device=x.device), self.scales[:, None, None], xt[None])  # (L, 3, N)
        cell = pos.floor()
        frac = pos - cell
        # Per-axis index terms of the lower and upper vertex: (c m) mod T and ((c + 1) m) mod T, in int64.
        lower = (cell.to(torch.int64) * self._mult) & mask
        terms = torch.empty(n_levels, 3, 2, n, dtype=torch.int32, device=x.device)
        terms[:, :, 0] = lower
        terms[:, :, 1] = (lower + self._mult) & mask
        tx, ty, tz = terms.unbind(1)  # (L, 2, N) each
        idx = torch.empty(n_levels, 2, 2, 2, n, dtype=torch.int32, device=x.device)
        nd = self.n_dense_levels
        if nd > 0:  # offset + i + j (res+1) + k (res+1)^2
            xy = tx[:nd, :, None] + ty[:nd, None, :]
            torch.add(xy[:, :, :, None], (tz[:nd] + self._level_offset[:nd])[:, None, None], out=idx[:nd])
        if nd < n_levels:  # offset + (i p0 ^ j p1 ^ k p2) mod T
            xy = tx[nd:, :, None] ^ ty[nd:, None, :]
            torch.bitwise_xor(xy[:, :, :, None], tz[nd:, None, None], out=idx[nd:])
            idx[nd:] += self._level_offset[nd:, :, :, None, None]
        w1 = torch.empty(n_levels, 3, 2, n, dtype=torch.float32, device=x.device)
        if torch.compiler.is_compiling():  # Dynamo refuses a non-contiguous out= (compile_training)
            w1[:, :, 0] = 1.0 - frac
        else:
            torch.sub(1.0, frac, out=w1[:, :, 0])
        w1[:, :, 1] = frac
        wx, wy, wz = w1.unbind(1)  # (L, 2, N) each
        w = (wx[:, :, None] * wy[:, None, :])[:, :, :, None] * wz[:, None, None]
        return idx.view(n_levels, 8, n), w.view(n_levels, 8, n)

    def forward(self, x: Tensor) -> Tensor:
        """Encode ``(N, 3)`` positions in ``[0, 1]^3`` to ``(N, L * F)`` float32 features (level-major)."""
        idx, w = self.corners(x)
        out = _Interpolate.apply(self.table, idx, w)  # (F, L, N)
        return out.permute(2, 1, 0).reshape(x.shape[0], self.out_dim)
