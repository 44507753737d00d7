"""An OpenVDB ``Tree_float_5_4_3`` tree: its topology (root, internal nodes, leaf masks) and node values
(:class:`TreeReader`), flattened to its active content (:class:`Tree`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nrc.volume.vdb.codecs import COMPRESS_ACTIVE_MASK, read_data
from nrc.volume.vdb.stream import Cursor

NODE_MASK_COMPRESSION = 222  # per-grid codec flags and per-node compression metadata

# Per-node compression metadata: how inactive values were dropped from a node's value array.
_NO_MASK_AND_ALL_VALS = 6  # schemes 0-5 store only the active values
_INACTIVE_VALUES_STORED = {2: 1, 4: 1, 5: 2}  # scheme -> number of explicit inactive values
_SELECTION_MASK_STORED = frozenset({3, 4, 5})  # schemes that store a selection bitmask

INTERNAL_LOG2 = (5, 4)  # log2 of the internal nodes' side lengths, top level first
LEAF_LOG2 = 3
LEAF_SIZE = 1 << (3 * LEAF_LOG2)
ROOT_CHILD_LOG2 = sum(INTERNAL_LOG2) + LEAF_LOG2  # a root tile spans 4096^3 voxels


@dataclass
class Tree:
    """An index-space tree flattened to its active content.

    ``leaf_values`` lists the active voxel values of all leaves in the order of
    ``np.nonzero(leaf_masks)``; tiles are active cubes of side ``tile_sizes`` at ``tile_origins``.
    """

    background: float
    leaf_origins: np.ndarray  # (L, 3) int64
    leaf_masks: np.ndarray  # (L, 512) bool, offset = x << 6 | y << 3 | z
    leaf_values: np.ndarray  # (A,) stored dtype
    tile_origins: np.ndarray  # (T, 3) int64
    tile_sizes: np.ndarray  # (T,) int64
    tile_values: np.ndarray  # (T,) float32


class TreeReader:
    """Reads one ``Tree_float_5_4_3`` tree (topology, then leaf buffers) after its transform."""

    def __init__(self, cur: Cursor, version: int, compression: int, dtype: np.dtype,
                 half: bool, grid_name: str) -> None:
        self.cur = cur
        self.modern = version >= NODE_MASK_COMPRESSION
        self.compression = compression
        self.dtype = dtype
        self.half = half
        self.stored = np.dtype("<f2") if half else dtype  # dtype of the values in node arrays
        self.grid_name = grid_name
        self.leaf_origins: list[np.ndarray] = []
        self.leaf_masks: list[np.ndarray] = []
        self.tile_origins: list[np.ndarray] = [np.zeros((0, 3), np.int64)]
        self.tile_sizes: list[np.ndarray] = [np.zeros(0, np.int64)]
        self.tile_values: list[np.ndarray] = [np.zeros(0, np.float32)]

    def read(self, block_pos: int) -> Tree:
        cur = self.cur
        if cur.i32(f"buffer count of grid '{self.grid_name}'") != 1:
            raise cur.error(f"unsupported multi-buffer tree in grid '{self.grid_name}'")
        background = float(cur.array(self.dtype, 1, "background value")[0])
        self._read_root()
        if cur.pos != block_pos:
            raise cur.error(f"corrupted file: topology of grid '{self.grid_name}' ends at offset "
                            f"{cur.pos}, but its data blocks start at {block_pos}")
        origins = np.concatenate([np.zeros((0, 3), np.int64), *self.leaf_origins])
        masks = np.concatenate([np.zeros((0, LEAF_SIZE), bool), *self.leaf_masks])
        return Tree(background, origins, masks, self._read_leaf_buffers(masks),
                     np.concatenate(self.tile_origins), np.concatenate(self.tile_sizes),
                     np.concatenate(self.tile_values))

    def _read_root(self) -> None:
        cur = self.cur
        num_tiles = cur.u32("root tile count")
        num_children = cur.u32("root child count")
        record = np.dtype([("origin", "<i4", 3), ("value", self.dtype), ("active", "u1")])
        tiles = cur.array(record, num_tiles, "root tiles")
        self._check_root_origins(tiles["origin"])
        active = tiles["active"] != 0
        self._add_tiles(tiles["origin"][active].astype(np.int64), ROOT_CHILD_LOG2,
                        tiles["value"][active])  # full precision even in half-float grids
        for _ in range(num_children):
            origin = cur.array("<i4", 3, "root child origin")
            self._check_root_origins(origin)
            self._read_internal(origin.astype(np.int64), 0)

    def _check_root_origins(self, origins: np.ndarray) -> None:
        if (origins & ((1 << ROOT_CHILD_LOG2) - 1)).any():
            raise self.cur.error(f"corrupted file: misaligned root node entry in grid "
                                 f"'{self.grid_name}' before offset {self.cur.pos}")

    def _read_internal(self, origin: np.ndarray, level: int) -> None:
        """An internal node's masks and tile values, then its children, depth first."""
        log2 = INTERNAL_LOG2[level]
        child_log2 = sum(INTERNAL_LOG2[level + 1:]) + LEAF_LOG2
        size = 1 << (3 * log2)
        child_mask = self._mask(size, "internal node child mask")
        value_mask = self._mask(size, "internal node value mask")
        if self.modern:
            active_values = self._read_values(size, value_mask, "internal node values")
            tile_values = active_values[~child_mask[value_mask]]
        else:  # only the non-child slots are stored
            tile_values = self._read_values(int(np.count_nonzero(~child_mask)),
                                            value_mask[~child_mask], "internal node values")
        tiles = np.flatnonzero(value_mask & ~child_mask)
        self._add_tiles(origin + (split_offsets(tiles, log2) << child_log2), child_log2,
                        tile_values)
        children = origin + (split_offsets(np.flatnonzero(child_mask), log2) << child_log2)
        if level + 1 < len(INTERNAL_LOG2):
            for child_origin in children:
                self._read_internal(child_origin, level + 1)
        else:
            masks = self.cur.array("u1", len(children) * LEAF_SIZE // 8, "leaf value masks")
            self.leaf_origins.append(children)
            self.leaf_masks.append(
                np.unpackbits(masks, bitorder="little").reshape(-1, LEAF_SIZE).astype(bool))

    def _read_leaf_buffers(self, masks: np.ndarray) -> np.ndarray:
        """The active values of every leaf, concatenated in leaf order."""
        cur = self.cur
        counts = np.count_nonzero(masks, axis=1).tolist()
        header = LEAF_SIZE // 8 + (0 if self.modern else 13)  # mask [+ origin and buffer count]
        values = []
        for mask, count in zip(masks, counts):
            head = cur.take(header, "leaf header")
            if not self.modern and head[-1] != 1:
                raise cur.error(f"unsupported multi-buffer leaf in grid '{self.grid_name}'")
            values.append(self._read_values(LEAF_SIZE, mask, "leaf values", count))
        return np.concatenate(values) if values else np.zeros(0, self.stored)

    def _add_tiles(self, origins: np.ndarray, log2: int, values: np.ndarray) -> None:
        self.tile_origins.append(origins)
        self.tile_sizes.append(np.full(len(origins), 1 << log2, np.int64))
        self.tile_values.append(values.astype(np.float32))

    def _mask(self, size: int, what: str) -> np.ndarray:
        return np.unpackbits(self.cur.array("u1", size // 8, what), bitorder="little").astype(bool)

    def _read_values(self, size: int, active: np.ndarray, what: str,
                     num_active: int | None = None) -> np.ndarray:
        """A node's values at its active positions (``np.flatnonzero(active)`` order).

        ``size`` values are stored, or only the active ones when the node is mask-compressed; the
        per-node metadata (from version 222) says which and precedes explicit inactive values and a
        selection mask, both skipped since inactive voxels read as background.
        """
        cur = self.cur
        if num_active is None:
            num_active = int(np.count_nonzero(active))
        scheme = _NO_MASK_AND_ALL_VALS
        if self.modern:
            scheme = cur.u8(f"{what} compression metadata")
            if scheme > _NO_MASK_AND_ALL_VALS:
                raise cur.error(f"corrupted file: unknown node compression metadata {scheme} "
                                f"in grid '{self.grid_name}' at offset {cur.pos - 1}")
            skip = _INACTIVE_VALUES_STORED.get(scheme, 0) * self.dtype.itemsize
            if scheme in _SELECTION_MASK_STORED:
                skip += size // 8
            cur.take(skip, f"{what} inactive values")
        masked = self.compression & COMPRESS_ACTIVE_MASK and scheme != _NO_MASK_AND_ALL_VALS
        count = num_active if masked else size
        values = read_data(self.cur, count, self.stored, self.half, self.compression, what,
                           self.grid_name)
        return values if count == num_active else values[active]


def split_offsets(offsets: np.ndarray, log2: int) -> np.ndarray:
    """Node-local linear offsets (x-major: ``x << 2 log2 | y << log2 | z``) -> (N, 3) int64 ijk."""
    offsets = offsets.astype(np.int64)
    mask = (1 << log2) - 1
    return np.stack([offsets >> (2 * log2), (offsets >> log2) & mask, offsets & mask], axis=1)
