"""Training-batch filters: which slices of the training-record buffer to train on this frame.

The NRC renderer traces one training path per training pixel (one pixel of the low-resolution training
image per screen tile) and writes that pixel's training records to a buffer in the memory order given
by :meth:`BatchFilter.order`. A filter looks at a boolean mask ``(H, W)`` over the training image (True
where the pixel's camera ray scatters in the medium) and returns the training batches as contiguous
slices ``(start, stop)`` of that buffer, in increasing buffer order.

Conventions:

* Flat pixel index ``p = y * W + x`` (row-major, ``y`` down the image rows, ``x`` across columns).
* ``order(H, W)[k]`` is the flat pixel index of the record at buffer position ``k`` (a permutation of
  ``range(H * W)``); ``buffer = per_pixel.reshape(H * W, ...)[order]``.
* Each filter's order is chosen so that every batch it can return is exactly one rectangle of pixels
  (tile order and memory layout agree, unlike the depth >= 2 quadtree of Fedotov 2024).

Filters, selected by ``name`` (see ``conf/batch_filter/``):

==============  =====================================================================================
``none``        ``n_batches`` equal contiguous batches of the row-major image, all trained.
``stripes``     ``n_stripes`` vertical strips; buffer strip by strip, row-major inside each strip;
                one batch per strip containing a True pixel.
``quadtree``    Fedotov 2024: ``2^depth x 2^depth`` leaves in Z-order (Morton: ``x`` in the even bits,
                ``y`` in the odd bits, so children go top-left, top-right, bottom-left, bottom-right),
                row-major inside a leaf. A leaf is active if any pixel is True; every maximal node whose
                leaves are all active is one merged batch.
==============  =====================================================================================

Image sizes that a filter cannot split evenly raise :class:`~nrc.errors.ConfigError` naming the key.
``batches`` returns Python ints, so it synchronises with the mask's device (a few small reductions).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.config import ConfigReader
from nrc.errors import ConfigError

Slices = list[tuple[int, int]]


class BatchFilter(ABC):
    """Chooses the training batches of a frame from the training image's scatter mask."""

    @abstractmethod
    def order(self, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
        """LongTensor ``(H * W,)``: the flat pixel index stored at each buffer position."""

    @abstractmethod
    def batches(self, mask: Tensor) -> Slices:
        """The batches ``(start, stop)`` to train for the bool ``mask`` ``(H, W)``, sorted by ``start``."""


def _check_mask(mask: Tensor) -> tuple[int, int]:
    if mask.dtype != torch.bool or mask.dim() != 2:
        raise ValueError(f"mask must be a bool tensor (H, W), got {mask.dtype} {tuple(mask.shape)}")
    return mask.shape[0], mask.shape[1]


@dataclass(frozen=True)
class NoFilter(BatchFilter):
    """Trains the whole image as ``n_batches`` equal row-major batches, whatever the mask."""

    n_batches: int = 4

    @classmethod
    def from_config(cls, cfg: ConfigReader) -> NoFilter:
        return cls(n_batches=cfg.get_int("n_batches", 4, lo=1))

    def _size(self, height: int, width: int) -> int:
        if (height * width) % self.n_batches:
            raise ConfigError(f"batch_filter.n_batches={self.n_batches} does not divide the training image "
                              f"{width}x{height} ({height * width} pixels)")
        return height * width // self.n_batches

    def order(self, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
        self._size(height, width)
        return torch.arange(height * width, device=device)

    def batches(self, mask: Tensor) -> Slices:
        size = self._size(*_check_mask(mask))
        return [(i * size, (i + 1) * size) for i in range(self.n_batches)]


@dataclass(frozen=True)
class StripeFilter(BatchFilter):
    """``n_stripes`` vertical strips of equal width; a strip without a True pixel is skipped.

    Buffer order: strip by strip (left to right), row-major inside a strip.
    """

    n_stripes: int = 8

    @classmethod
    def from_config(cls, cfg: ConfigReader) -> StripeFilter:
        return cls(n_stripes=cfg.get_int("n_stripes", 8, lo=1))

    def _width(self, width: int) -> int:
        if width % self.n_stripes:
            raise ConfigError(f"batch_filter.n_stripes={self.n_stripes} does not divide the training image "
                              f"width {width}")
        return width // self.n_stripes

    def order(self, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
        sw = self._width(width)
        k = torch.arange(height * width, device=device)
        strip, r = k // (height * sw), k % (height * sw)
        return (r // sw) * width + strip * sw + r % sw

    def batches(self, mask: Tensor) -> Slices:
        height, width = _check_mask(mask)
        sw = self._width(width)
        strips = mask.view(height, self.n_stripes, sw).any(dim=2).any(dim=0).nonzero().squeeze(1)
        span = height * sw
        return [(s * span, (s + 1) * span) for s in strips.tolist()]


def morton_decode(codes: Tensor, bits: int) -> tuple[Tensor, Tensor]:
    """``(y, x)`` of Z-order ``codes`` with ``bits`` bits per axis (``x`` in the even bits, ``y`` in the odd)."""
    y = torch.zeros_like(codes)
    x = torch.zeros_like(codes)
    for b in range(bits):
        x |= ((codes >> (2 * b)) & 1) << b
        y |= ((codes >> (2 * b + 1)) & 1) << b
    return y, x


@dataclass(frozen=True)
class QuadtreeFilter(BatchFilter):
    """Fedotov's quadtree of depth ``depth``; tile order and memory layout agree at every depth.

    Leaves are ``(H / 2^depth) x (W / 2^depth)`` pixel tiles stored in Z-order, row-major inside a leaf,
    so the node with Z-index ``m`` at level ``l`` (``4^l`` nodes) is the buffer slice
    ``[m * s, (m + 1) * s)`` with ``s = 4^(depth - l) * leaf pixels``. Selection, top-down: a node whose
    leaves are all active is one batch; otherwise its active children are handled alike; inactive leaves
    yield nothing. Equivalently, the batches are the all-active nodes whose parent is not all-active.
    """

    depth: int = 3

    @classmethod
    def from_config(cls, cfg: ConfigReader) -> QuadtreeFilter:
        return cls(depth=cfg.get_int("depth", 3, lo=0, hi=15))

    def _leaf(self, height: int, width: int) -> tuple[int, int]:
        n = 1 << self.depth
        if height % n or width % n:
            raise ConfigError(f"batch_filter.depth={self.depth} needs a training image whose width and height are "
                              f"multiples of {n}, got {width}x{height}")
        return height // n, width // n

    def order(self, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
        th, tw = self._leaf(height, width)
        k = torch.arange(height * width, device=device)
        leaf, r = k // (th * tw), k % (th * tw)
        ly, lx = morton_decode(leaf, self.depth)
        return (ly * th + r // tw) * width + lx * tw + r % tw

    def batches(self, mask: Tensor) -> Slices:
        height, width = _check_mask(mask)
        th, tw = self._leaf(height, width)
        n = 1 << self.depth
        ly, lx = morton_decode(torch.arange(n * n, device=mask.device), self.depth)
        # full[l][m]: every leaf under node m of level l is active (the four children of m are 4m..4m+3).
        full = [mask.view(n, th, n, tw).any(dim=3).any(dim=1)[ly, lx]]
        for _ in range(self.depth):
            full.insert(0, full[0].view(-1, 4).all(dim=1))
        starts, sizes = [], []
        for level, f in enumerate(full):
            if level > 0:
                f = f & ~full[level - 1].repeat_interleave(4)
            node = f.nonzero().squeeze(1)
            span = 4 ** (self.depth - level) * th * tw
            starts.append(node * span)
            sizes.append(torch.full_like(node, span))
        start, size = torch.cat(starts), torch.cat(sizes)
        rank = start.argsort()
        return [(a, a + b) for a, b in zip(start[rank].tolist(), size[rank].tolist())]


BATCH_FILTERS: dict[str, type[NoFilter] | type[StripeFilter] | type[QuadtreeFilter]] = {
    "none": NoFilter,
    "stripes": StripeFilter,
    "quadtree": QuadtreeFilter,
}


def make_batch_filter(cfg: Mapping[str, Any] | Any, path: str = "batch_filter") -> BatchFilter:
    """The filter configured by the mapping ``cfg`` (``name`` plus that filter's parameters).

    Unknown names and keys raise :class:`~nrc.errors.ConfigError` naming the key under ``path``.
    """
    reader = ConfigReader(cfg, path)
    name = reader.get_choice("name", sorted(BATCH_FILTERS))
    batch_filter = BATCH_FILTERS[name].from_config(reader)
    reader.finish()
    return batch_filter


def _ellipse(height: int, width: int, cy: float, cx: float, ry: float, rx: float) -> Tensor:
    """Bool ``(H, W)``: pixel centres inside the axis-aligned ellipse (in pixel units)."""
    y = torch.arange(height, dtype=torch.float64)[:, None] + 0.5
    x = torch.arange(width, dtype=torch.float64)[None, :] + 0.5
    return ((y - cy) / ry) ** 2 + ((x - cx) / rx) ** 2 <= 1.0


def count_batches_demo(width: int = 64, height: int = 32, depth: int = 3, n_stripes: int = 8,
                       n_batches: int = 4) -> dict[str, dict[str, int]]:
    """Batches trained per filter for three views of a cloud on a ``width x height`` training image.

    Masks: ``whole`` (a centred ellipse covering ~60 % of the image), ``quarter`` (the same ellipse
    shrunk into the top-left quadrant) and ``none`` (nothing in view). Returns ``{mask: {filter: count}}``.
    """
    s = math.sqrt(0.6 * 4 / math.pi)  # semi-axes s * (W/2, H/2) cover 60 % of the image
    masks = {
        "whole": _ellipse(height, width, height / 2, width / 2, s * height / 2, s * width / 2),
        "quarter": _ellipse(height, width, height / 4, width / 4, s * height / 4, s * width / 4),
        "none": torch.zeros(height, width, dtype=torch.bool),
    }
    filters: dict[str, BatchFilter] = {
        "none": NoFilter(n_batches), "stripes": StripeFilter(n_stripes), "quadtree": QuadtreeFilter(depth),
    }
    return {m: {f: len(flt.batches(mask)) for f, flt in filters.items()} for m, mask in masks.items()}
