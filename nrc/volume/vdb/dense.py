"""A tree's active voxels and tiles scattered into a dense array over the active index bounding box
(:func:`densify`)."""

from __future__ import annotations

import numpy as np

from nrc.volume.vdb.stream import Cursor
from nrc.volume.vdb.tree import LEAF_LOG2, Tree

_MAX_DENSE_VOXELS = 1 << 30  # 4 GiB of float32; larger active boxes are refused


def densify(tree: Tree, cur: Cursor) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Scatter a tree's active voxels and tiles into a dense array over the active bounding box.

    Returns the array and the index of its first voxel.

    Works on a leaf-aligned (multiple-of-8) padding of the box, so whole leaves are written at once,
    then crops to the box.
    """
    counts = np.count_nonzero(tree.leaf_masks, axis=1)
    if counts.sum() != len(tree.leaf_values):
        raise cur.error("corrupted file: leaf value count does not match the active voxel count")
    blocks = np.full(tree.leaf_masks.shape, tree.background, np.float32)
    blocks[tree.leaf_masks] = tree.leaf_values
    occupied = counts > 0  # leaves without active voxels are background only, maybe outside the box
    origins = tree.leaf_origins[occupied]
    blocks = blocks[occupied].reshape(-1, *(3 * (1 << LEAF_LOG2,)))
    lo, hi = _leaf_bounds(origins, tree.leaf_masks[occupied])
    tile_hi = tree.tile_origins + tree.tile_sizes[:, None] - 1
    lo = np.concatenate([lo, tree.tile_origins]).min(axis=0, initial=np.iinfo(np.int64).max)
    hi = np.concatenate([hi, tile_hi]).max(axis=0, initial=np.iinfo(np.int64).min)
    if (lo > hi).any():
        return np.zeros((0, 0, 0), np.float32), (0, 0, 0)
    shape = hi - lo + 1
    if int(np.prod(shape, dtype=np.float64)) > _MAX_DENSE_VOXELS:
        raise cur.error(f"active bounding box {lo.tolist()}..{hi.tolist()} is too large for a "
                        f"dense array ({' x '.join(map(str, shape.tolist()))} voxels)")
    leaf = 1 << LEAF_LOG2
    lo_pad = lo & ~(leaf - 1)
    nblocks = ((hi | (leaf - 1)) - lo_pad + 1) // leaf
    padded = np.full(tuple((nblocks * leaf).tolist()), tree.background, np.float32)
    for start, stop, value in zip((tree.tile_origins - lo_pad).tolist(),
                                  (tile_hi - lo_pad + 1).tolist(),
                                  tree.tile_values.tolist()):
        padded[start[0]:stop[0], start[1]:stop[1], start[2]:stop[2]] = value
    as_blocks = padded.reshape(nblocks[0], leaf, nblocks[1], leaf, nblocks[2], leaf)
    index = (origins - lo_pad) >> LEAF_LOG2
    as_blocks.transpose(0, 2, 4, 1, 3, 5)[index[:, 0], index[:, 1], index[:, 2]] = blocks
    begin, end = lo - lo_pad, hi - lo_pad + 1
    values = np.ascontiguousarray(padded[begin[0]:end[0], begin[1]:end[1], begin[2]:end[2]])
    return values, (int(lo[0]), int(lo[1]), int(lo[2]))


def _leaf_bounds(origins: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-leaf inclusive index bounds ``(lo, hi)``, each (L, 3), of the active voxels."""
    side = 1 << LEAF_LOG2
    cubes = masks.reshape(-1, side, side, side)
    lo = np.empty_like(origins)
    hi = np.empty_like(origins)
    for axis in range(3):
        others = tuple(a for a in (1, 2, 3) if a != axis + 1)
        occupied = cubes.any(axis=others)  # (L, side)
        lo[:, axis] = occupied.argmax(axis=1)
        hi[:, axis] = side - 1 - occupied[:, ::-1].argmax(axis=1)
    return origins + lo, origins + hi
