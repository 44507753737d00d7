"""Training-batch filters: quadtree selection against a brute-force recursion, tile order == memory layout."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from conftest import CONF_DIR
from nrc.errors import ConfigError
from nrc.render.radiance_caching.batch_filter import (NoFilter, QuadtreeFilter, StripeFilter, count_batches_demo,
                                     make_batch_filter)

Rect = tuple[int, int, int, int]  # y0, x0, height, width


def reference_quadtree(mask: torch.Tensor, depth: int) -> list[Rect]:
    """Fedotov's selection by plain recursion over pixel rectangles."""
    height, width = mask.shape
    th, tw = height >> depth, width >> depth

    def leaves_active(y0: int, x0: int, h: int, w: int) -> bool:
        return all(bool(mask[y:y + th, x:x + tw].any()) for y in range(y0, y0 + h, th) for x in range(x0, x0 + w, tw))

    def visit(y0: int, x0: int, h: int, w: int) -> list[Rect]:
        if not mask[y0:y0 + h, x0:x0 + w].any():
            return []
        if leaves_active(y0, x0, h, w):
            return [(y0, x0, h, w)]
        h2, w2 = h // 2, w // 2
        return [r for dy in (0, h2) for dx in (0, w2) for r in visit(y0 + dy, x0 + dx, h2, w2)]

    return visit(0, 0, height, width)


def rect_pixels(rect: Rect, width: int) -> frozenset[int]:
    y0, x0, h, w = rect
    return frozenset(y * width + x for y in range(y0, y0 + h) for x in range(x0, x0 + w))


def slice_pixels(order: torch.Tensor, batch: tuple[int, int]) -> frozenset[int]:
    return frozenset(order[batch[0]:batch[1]].tolist())


def random_mask(gen: torch.Generator, depth: int, th: int, tw: int, kind: str, p: float) -> torch.Tensor:
    """Pixel-level noise (``kind='pixel'``) or whole random leaves (``'leaf'``, which makes merges likely)."""
    n = 1 << depth
    if kind == "pixel":
        return torch.rand(n * th, n * tw, generator=gen) < p
    leaves = torch.rand(n, n, generator=gen) < p
    return leaves.repeat_interleave(th, 0).repeat_interleave(tw, 1)


def check_layout(order: torch.Tensor, batches: list[tuple[int, int]], n: int) -> None:
    assert sorted(order.tolist()) == list(range(n))  # a permutation
    assert batches == sorted(batches)
    assert all(a < b for a, b in batches)
    assert all(b0 <= a1 for (_, b0), (a1, _) in zip(batches, batches[1:]))  # disjoint


# Densities from all-False to all-True; whole random leaves make merged nodes of every size likely.
MASKS = [(kind, p, seed) for kind, ps in (("pixel", (0.0, 0.02, 0.1, 0.5, 1.0)), ("leaf", (0.5, 0.8, 0.95)))
         for p in ps for seed in range(6)]


@pytest.mark.parametrize("depth", (1, 2, 3, 4))
def test_quadtree_matches_brute_force(depth: int) -> None:
    """Same nodes as the recursion; each slice is exactly its node's rectangle; union = active leaves."""
    for kind, p, seed in MASKS:
        gen = torch.Generator().manual_seed(1000 * depth + seed + int(100 * p))
        th, tw = (int(v) for v in torch.randint(1, 4, (2,), generator=gen))
        mask = random_mask(gen, depth, th, tw, kind, p)
        height, width = mask.shape
        qt = QuadtreeFilter(depth)
        order, batches = qt.order(height, width), qt.batches(mask)
        check_layout(order, batches, height * width)
        expected = reference_quadtree(mask, depth)
        got = [slice_pixels(order, b) for b in batches]
        assert set(got) == {rect_pixels(r, width) for r in expected}, (depth, kind, p, seed)
        assert len(got) == len(expected)
        # Merged batches are whole nodes: 4^k leaves (size) at a multiple of their own size (position).
        for a, b in batches:
            leaves = (b - a) // (th * tw)
            assert (b - a) % (th * tw) == 0 and leaves & (leaves - 1) == 0 and (leaves.bit_length() - 1) % 2 == 0
            assert a % (b - a) == 0
        # The union is exactly the pixels of the active leaves.
        n = 1 << depth
        active = mask.view(n, th, n, tw).any(3).any(1)
        active_pixels = active.repeat_interleave(th, 0).repeat_interleave(tw, 1).flatten().nonzero().squeeze(1)
        covered = set().union(*got) if got else set()
        assert covered == set(active_pixels.tolist())


def test_quadtree_extremes() -> None:
    qt = QuadtreeFilter(3)
    assert qt.batches(torch.zeros(16, 24, dtype=torch.bool)) == []
    assert qt.batches(torch.ones(16, 24, dtype=torch.bool)) == [(0, 16 * 24)]
    one = torch.zeros(16, 24, dtype=torch.bool)
    one[15, 23] = True  # bottom-right leaf: the last in Z-order
    assert qt.batches(one) == [(16 * 24 - 6, 16 * 24)]


def test_quadtree_order_is_z_order_of_row_major_leaves() -> None:
    order = QuadtreeFilter(2).order(4, 8).view(4, 8)
    assert order.tolist() == [[0, 1, 2, 3, 8, 9, 10, 11], [4, 5, 6, 7, 12, 13, 14, 15],
                              [16, 17, 18, 19, 24, 25, 26, 27], [20, 21, 22, 23, 28, 29, 30, 31]]


def test_stripes_skip_empty_strips() -> None:
    height, width, n = 6, 12, 4
    sf = StripeFilter(n)
    order = sf.order(height, width)
    mask = torch.zeros(height, width, dtype=torch.bool)
    assert sf.batches(mask) == []
    mask[5, 3] = True   # strip 1 (columns 3..5)
    mask[0, 11] = True  # strip 3 (columns 9..11)
    batches = sf.batches(mask)
    check_layout(order, batches, height * width)
    assert batches == [(18, 36), (54, 72)]
    for (a, b), s in zip(batches, (1, 3)):
        assert slice_pixels(order, (a, b)) == rect_pixels((0, 3 * s, height, 3), width)
    assert len(sf.batches(torch.ones(height, width, dtype=torch.bool))) == n


def test_none_trains_everything() -> None:
    nf = NoFilter(4)
    for mask in (torch.zeros(4, 6, dtype=torch.bool), torch.ones(4, 6, dtype=torch.bool)):
        assert nf.batches(mask) == [(0, 6), (6, 12), (12, 18), (18, 24)]
    assert torch.equal(nf.order(4, 6), torch.arange(24))


def test_configs_and_errors() -> None:
    for name, cls in (("none", NoFilter), ("stripes", StripeFilter), ("quadtree", QuadtreeFilter)):
        assert isinstance(make_batch_filter(OmegaConf.load(CONF_DIR / "batch_filter" / f"{name}.yaml")), cls)
    assert make_batch_filter({"name": "quadtree", "depth": 2}) == QuadtreeFilter(2)
    with pytest.raises(ConfigError, match="batch_filter.name"):
        make_batch_filter({"name": "octree"})
    with pytest.raises(ConfigError, match="levels"):
        make_batch_filter({"name": "quadtree", "levels": 3})
    with pytest.raises(ConfigError, match="batch_filter.n_stripes"):
        make_batch_filter({"name": "stripes", "n_stripes": 0})
    with pytest.raises(ConfigError, match="batch_filter.depth"):
        QuadtreeFilter(3).batches(torch.ones(12, 16, dtype=torch.bool))
    with pytest.raises(ConfigError, match="batch_filter.n_stripes"):
        StripeFilter(5).order(4, 12)
    with pytest.raises(ConfigError, match="batch_filter.n_batches"):
        NoFilter(5).batches(torch.ones(4, 6, dtype=torch.bool))


def test_count_batches_demo() -> None:
    counts = count_batches_demo()
    assert counts["none"] == {"none": 4, "stripes": 0, "quadtree": 0}
    assert counts["whole"]["stripes"] == 8 and counts["quarter"]["stripes"] == 4
    assert counts["quarter"]["quadtree"] <= counts["whole"]["quadtree"]
