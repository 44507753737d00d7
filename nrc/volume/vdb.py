"""Pure-numpy reader for OpenVDB (``.vdb``) files: scalar float grids to dense arrays.

Conventions:

* :func:`read_vdb` returns ``D`` of shape ``(nx, ny, nz)``, dtype float32, over the grid's *active*
  index-space bounding box ``[xmin, xmax] x [ymin, ymax] x [zmin, zmax]`` (inclusive), with
  ``D[i - xmin, j - ymin, k - zmin]`` the value of voxel ``(i, j, k)``: ``i`` runs along index x,
  ``j`` along y, ``k`` along z. Active tiles fill their whole region (8^3, 128^3 or 4096^3 voxels)
  clipped to that box. Inactive voxels are the grid's background value (0 for density grids). A grid
  with no active voxel gives a ``(0, 0, 0)`` array. The grid's transform (voxel size, placement in
  world space) is not applied.
* Grids are named as in the file; ``grid=None`` takes the first scalar float grid.

Supported: file format versions 220 to 224 (224 is the current one), grids of type
``Tree_float_5_4_3``, half-float storage, active tiles at every level, the codecs none, zip and
blosc (blosc through the optional ``blosc`` package), all per-node mask-compression schemes,
several grids per file, and instanced grids (which share their parent's tree). Not supported:
other value types (double, half, vector, integer, bool, point grids) and tree configurations,
files written to a stream without grid offsets, dense boxes of more than 2^30 voxels. Every
failure - a missing, truncated, corrupted or unsupported file - raises
:class:`~nrc.errors.VDBError` naming the file and the problem.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from nrc.errors import VDBError

__all__ = ["VDBGrid", "list_vdb_grids", "read_vdb", "read_vdb_grid"]

_MAGIC = 0x56444220  # "VDB " as a little-endian int64
_MIN_VERSION = 220  # OPENVDB_FILE_VERSION_SELECTIVE_COMPRESSION
_MAX_VERSION = 224  # OPENVDB_FILE_VERSION_MULTIPASS_IO, the current version
_FLOAT_FRUSTUM_BBOX = 221  # from this version on, frustum maps store a float bounding box
_NODE_MASK_COMPRESSION = 222  # per-grid codec flags and per-node compression metadata

_COMPRESS_ZIP = 0x1
_COMPRESS_ACTIVE_MASK = 0x2
_COMPRESS_BLOSC = 0x4
_COMPRESS_ALL = _COMPRESS_ZIP | _COMPRESS_ACTIVE_MASK | _COMPRESS_BLOSC

# Per-node compression metadata: how inactive values were dropped from a node's value array.
_NO_MASK_AND_ALL_VALS = 6  # schemes 0-5 store only the active values
_INACTIVE_VALUES_STORED = {2: 1, 4: 1, 5: 2}  # scheme -> number of explicit inactive values
_SELECTION_MASK_STORED = frozenset({3, 4, 5})  # schemes that store a selection bitmask

_HALF_SUFFIX = "_HalfFloat"
_NAME_SEPARATOR = "\x1e"  # unique grid names are "name<SEP>index" when names repeat
_VALUE_TYPES = {"Tree_float_5_4_3": np.dtype("<f4")}  # supported grid type -> value dtype
_INTERNAL_LOG2 = (5, 4)  # log2 of the internal nodes' side lengths, top level first
_LEAF_LOG2 = 3
_LEAF_SIZE = 1 << (3 * _LEAF_LOG2)
_ROOT_CHILD_LOG2 = sum(_INTERNAL_LOG2) + _LEAF_LOG2  # a root tile spans 4096^3 voxels

# Transform maps: type name -> stored size in bytes (doubles: Vec3d = 24, Mat4d = 128).
_MAP_SIZES = {
    "AffineMap": 128,
    "UnitaryMap": 128,
    "ScaleMap": 5 * 24,
    "UniformScaleMap": 5 * 24,
    "ScaleTranslateMap": 6 * 24,
    "UniformScaleTranslateMap": 6 * 24,
    "TranslationMap": 24,
}
_FRUSTUM_MAP = "NonlinearFrustumMap"

_MAX_DENSE_VOXELS = 1 << 30  # 4 GiB of float32; larger active boxes are refused


class _Cursor:
    """Bounds-checked little-endian reads over a file's bytes.

    Every read is checked against the remaining size; failures raise :class:`VDBError` naming the
    file, the offset and what was being read.
    """

    def __init__(self, data: bytes, path: str) -> None:
        self.buf = memoryview(data)
        self.pos = 0
        self.path = path

    def error(self, message: str) -> VDBError:
        return VDBError(f"{self.path}: {message}")

    def seek(self, pos: int, what: str) -> None:
        if not 0 <= pos <= len(self.buf):
            raise self.error(f"corrupted file: {what} offset {pos} lies outside the file "
                             f"({len(self.buf)} bytes)")
        self.pos = pos

    def take(self, n: int, what: str) -> memoryview:
        end = self.pos + n
        if n < 0 or end > len(self.buf):
            raise self.error(f"truncated or corrupted file: {what} needs {n} bytes at offset "
                             f"{self.pos}, but only {len(self.buf) - self.pos} remain")
        view = self.buf[self.pos:end]
        self.pos = end
        return view

    def unpack(self, fmt: str, what: str) -> int:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt), what))[0]

    def u8(self, what: str) -> int:
        return self.unpack("<B", what)

    def i32(self, what: str) -> int:
        return self.unpack("<i", what)

    def u32(self, what: str) -> int:
        return self.unpack("<I", what)

    def i64(self, what: str) -> int:
        return self.unpack("<q", what)

    def string(self, what: str) -> str:
        raw = self.take(self.u32(f"length of {what}"), what)
        try:
            return bytes(raw).decode("utf-8")
        except UnicodeDecodeError:
            raise self.error(f"corrupted file: {what} is not valid UTF-8") from None

    def array(self, dtype: np.dtype | str, count: int, what: str) -> np.ndarray:
        dtype = np.dtype(dtype)
        return np.frombuffer(self.take(count * dtype.itemsize, what), dtype)


@dataclass(frozen=True)
class _GridDescriptor:
    """One grid's entry in the file's grid table; positions are byte offsets into the file."""

    unique_name: str
    type_name: str  # without the half-float suffix
    half_suffix: bool
    parent: str  # unique name of the instance parent, "" unless the grid is an instance
    grid_pos: int
    block_pos: int
    end_pos: int

    @property
    def name(self) -> str:
        return self.unique_name.split(_NAME_SEPARATOR)[0]


@dataclass(frozen=True)
class _File:
    cur: _Cursor
    version: int
    compression: int  # file-wide codec flags, used only by versions before 222
    grids: list[_GridDescriptor]


@dataclass
class _Tree:
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


def list_vdb_grids(path: str | PathLike[str]) -> list[tuple[str, str]]:
    """The ``(name, type)`` of every grid in the file, in file order.

    ``type`` is the tree type as stored, without the half-float suffix, e.g. ``"Tree_float_5_4_3"``
    or ``"Tree_vec3s_5_4_3"``.
    """
    return [(gd.name, gd.type_name) for gd in _open(path).grids]


def read_vdb(path: str | PathLike[str], grid: str | None = None) -> np.ndarray:
    """Read one scalar float grid of an OpenVDB file as a dense float32 array.

    Args:
        path: the ``.vdb`` file.
        grid: the grid's name; ``None`` takes the first grid of a supported float type.

    Returns:
        ``D`` of shape ``(nx, ny, nz)`` over the active index bounding box, with
        ``D[i - xmin, j - ymin, k - zmin]`` the value of voxel ``(i, j, k)`` and inactive voxels at
        the background value (see the module docstring).

    Raises:
        VDBError: the file is missing, truncated, corrupted or unsupported, the named grid does not
            exist (the message lists the file's grids), or the grid is not a supported float grid.
    """
    return read_vdb_grid(path, grid).values


@dataclass(frozen=True)
class VDBGrid:
    """A grid read by :func:`read_vdb_grid`.

    ``values[i, j, k]`` is voxel ``origin + (i, j, k)``, so the active index bounding box is
    ``origin`` to ``origin + values.shape - 1`` inclusive.
    """

    name: str
    values: np.ndarray  # (nx, ny, nz) float32
    origin: tuple[int, int, int]  # index (xmin, ymin, zmin); (0, 0, 0) for an empty grid
    background: float


def read_vdb_grid(path: str | PathLike[str], grid: str | None = None) -> VDBGrid:
    """Like :func:`read_vdb`, also returning the grid's name, index origin and background value."""
    vdb = _open(path)
    gd = _select_grid(vdb, grid)
    tree = _read_tree(vdb, gd)
    values, origin = _densify(tree, vdb.cur)
    return VDBGrid(gd.name, values, origin, tree.background)


def _open(path: str | PathLike[str]) -> _File:
    """Read the header, the file metadata and the grid table of ``path``."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise VDBError(f"{path}: cannot read OpenVDB file: {exc.strerror or exc}") from exc
    cur = _Cursor(data, str(path))
    if len(data) < 8 or cur.i64("magic number") != _MAGIC:
        raise cur.error("not an OpenVDB file (bad magic number)")
    version = cur.u32("file format version")
    if not _MIN_VERSION <= version <= _MAX_VERSION:
        raise cur.error(f"unsupported OpenVDB file format version {version} "
                        f"(supported: {_MIN_VERSION}-{_MAX_VERSION})")
    cur.take(8, "library version")
    if cur.u8("grid-offsets flag") == 0:
        raise cur.error("unsupported file: written as a stream without grid offsets")
    compression = _COMPRESS_ZIP | _COMPRESS_ACTIVE_MASK
    if version < _NODE_MASK_COMPRESSION:
        compression = _COMPRESS_ZIP if cur.u8("compression flag") else 0
    cur.take(36, "file UUID")
    _read_metadata(cur, "file metadata")
    return _File(cur, version, compression, _read_grid_table(cur))


def _read_metadata(cur: _Cursor, what: str) -> dict[str, tuple[str, memoryview]]:
    """A metadata table: name -> (type name, raw value bytes)."""
    entries = {}
    for _ in range(cur.u32(f"{what} count")):
        name = cur.string(f"{what} name")
        type_name = cur.string(f"type of {what} '{name}'")
        size = cur.u32(f"size of {what} '{name}'")
        entries[name] = (type_name, cur.take(size, f"{what} '{name}'"))
    return entries


def _read_grid_table(cur: _Cursor) -> list[_GridDescriptor]:
    """The grid descriptors, each followed in the file by its grid's data up to ``end_pos``."""
    count = cur.i32("grid count")
    if count < 0:
        raise cur.error(f"corrupted file: negative grid count {count}")
    grids = []
    for _ in range(count):
        unique_name = cur.string("grid name")
        type_name = cur.string(f"type of grid '{unique_name}'")
        half = type_name.endswith(_HALF_SUFFIX)
        if half:
            type_name = type_name[: -len(_HALF_SUFFIX)]
        parent = cur.string(f"instance parent of grid '{unique_name}'")
        grid_pos, block_pos, end_pos = (cur.i64(f"offsets of grid '{unique_name}'")
                                        for _ in range(3))
        if not cur.pos <= grid_pos <= end_pos <= len(cur.buf):
            raise cur.error(f"corrupted file: grid '{unique_name}' has invalid offsets "
                            f"({grid_pos}, {end_pos}) for a file of {len(cur.buf)} bytes")
        grids.append(_GridDescriptor(unique_name, type_name, half, parent, grid_pos, block_pos,
                                     end_pos))
        cur.seek(end_pos, f"end of grid '{unique_name}'")
    return grids


def _select_grid(vdb: _File, name: str | None) -> _GridDescriptor:
    """The grid called ``name``, or the first supported float grid when ``name`` is None."""
    listing = ", ".join(f"'{gd.name}' ({gd.type_name})" for gd in vdb.grids) or "none"
    if name is None:
        for gd in vdb.grids:
            if gd.type_name in _VALUE_TYPES:
                return gd
        raise vdb.cur.error(f"no float grid in the file; grids: {listing}")
    for gd in vdb.grids:
        if name in (gd.name, gd.unique_name):
            if gd.type_name not in _VALUE_TYPES:
                raise vdb.cur.error(f"grid '{gd.name}' has unsupported type {gd.type_name} "
                                    f"(supported: {', '.join(_VALUE_TYPES)})")
            return gd
    raise vdb.cur.error(f"no grid named '{name}'; grids: {listing}")


def _read_tree(vdb: _File, gd: _GridDescriptor) -> _Tree:
    """Parse a grid's compression flags, metadata, transform, topology and leaf buffers."""
    cur = vdb.cur
    if gd.parent:
        parents = [p for p in vdb.grids if p.unique_name == gd.parent and not p.parent]
        if not parents:
            raise cur.error(f"grid '{gd.name}' is an instance of missing grid '{gd.parent}'")
        return _read_tree(vdb, parents[0])
    cur.seek(gd.grid_pos, f"start of grid '{gd.name}'")
    compression = vdb.compression
    if vdb.version >= _NODE_MASK_COMPRESSION:
        compression = cur.u32(f"compression flags of grid '{gd.name}'")
    if compression & ~_COMPRESS_ALL:
        raise cur.error(f"unsupported compression flags {compression:#x} in grid '{gd.name}'")
    metadata = _read_metadata(cur, f"metadata of grid '{gd.name}'")
    half_meta = metadata.get("is_saved_as_half_float")
    half = gd.half_suffix or (half_meta is not None and half_meta[0] == "bool"
                              and any(bytes(half_meta[1])))
    _skip_transform(cur, vdb.version, gd.name)
    reader = _TreeReader(cur, vdb.version, compression, _VALUE_TYPES[gd.type_name], half, gd.name)
    return reader.read(gd.block_pos)


def _skip_transform(cur: _Cursor, version: int, grid_name: str) -> None:
    """Step over the grid's index-to-world transform (not needed in index space)."""
    what = f"transform of grid '{grid_name}'"
    map_type = cur.string(what)
    if map_type in _MAP_SIZES:
        cur.take(_MAP_SIZES[map_type], what)
    elif map_type == _FRUSTUM_MAP:
        cur.take(48 if version >= _FLOAT_FRUSTUM_BBOX else 24, what)  # bounding box
        cur.take(16, what)  # taper, depth
        cur.string(what)  # type of the second map, always an affine map
        cur.take(_MAP_SIZES["AffineMap"], what)
    else:
        raise cur.error(f"unsupported transform map type '{map_type}' in grid '{grid_name}'")


class _TreeReader:
    """Reads one ``Tree_float_5_4_3`` tree (topology, then leaf buffers) after its transform."""

    def __init__(self, cur: _Cursor, version: int, compression: int, dtype: np.dtype,
                 half: bool, grid_name: str) -> None:
        self.cur = cur
        self.modern = version >= _NODE_MASK_COMPRESSION
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

    def read(self, block_pos: int) -> _Tree:
        cur = self.cur
        if cur.i32(f"buffer count of grid '{self.grid_name}'") != 1:
            raise cur.error(f"unsupported multi-buffer tree in grid '{self.grid_name}'")
        background = float(cur.array(self.dtype, 1, "background value")[0])
        self._read_root()
        if cur.pos != block_pos:
            raise cur.error(f"corrupted file: topology of grid '{self.grid_name}' ends at offset "
                            f"{cur.pos}, but its data blocks start at {block_pos}")
        origins = np.concatenate([np.zeros((0, 3), np.int64), *self.leaf_origins])
        masks = np.concatenate([np.zeros((0, _LEAF_SIZE), bool), *self.leaf_masks])
        return _Tree(background, origins, masks, self._read_leaf_buffers(masks),
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
        self._add_tiles(tiles["origin"][active].astype(np.int64), _ROOT_CHILD_LOG2,
                        tiles["value"][active])  # full precision even in half-float grids
        for _ in range(num_children):
            origin = cur.array("<i4", 3, "root child origin")
            self._check_root_origins(origin)
            self._read_internal(origin.astype(np.int64), 0)

    def _check_root_origins(self, origins: np.ndarray) -> None:
        if (origins & ((1 << _ROOT_CHILD_LOG2) - 1)).any():
            raise self.cur.error(f"corrupted file: misaligned root node entry in grid "
                                 f"'{self.grid_name}' before offset {self.cur.pos}")

    def _read_internal(self, origin: np.ndarray, level: int) -> None:
        """An internal node's masks and tile values, then its children, depth first."""
        log2 = _INTERNAL_LOG2[level]
        child_log2 = sum(_INTERNAL_LOG2[level + 1:]) + _LEAF_LOG2
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
        self._add_tiles(origin + (_split_offsets(tiles, log2) << child_log2), child_log2,
                        tile_values)
        children = origin + (_split_offsets(np.flatnonzero(child_mask), log2) << child_log2)
        if level + 1 < len(_INTERNAL_LOG2):
            for child_origin in children:
                self._read_internal(child_origin, level + 1)
        else:
            masks = self.cur.array("u1", len(children) * _LEAF_SIZE // 8, "leaf value masks")
            self.leaf_origins.append(children)
            self.leaf_masks.append(
                np.unpackbits(masks, bitorder="little").reshape(-1, _LEAF_SIZE).astype(bool))

    def _read_leaf_buffers(self, masks: np.ndarray) -> np.ndarray:
        """The active values of every leaf, concatenated in leaf order."""
        cur = self.cur
        counts = np.count_nonzero(masks, axis=1).tolist()
        header = _LEAF_SIZE // 8 + (0 if self.modern else 13)  # mask [+ origin and buffer count]
        values = []
        for mask, count in zip(masks, counts):
            head = cur.take(header, "leaf header")
            if not self.modern and head[-1] != 1:
                raise cur.error(f"unsupported multi-buffer leaf in grid '{self.grid_name}'")
            values.append(self._read_values(_LEAF_SIZE, mask, "leaf values", count))
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
        masked = self.compression & _COMPRESS_ACTIVE_MASK and scheme != _NO_MASK_AND_ALL_VALS
        count = num_active if masked else size
        values = self._read_data(count, what)
        return values if count == num_active else values[active]

    def _read_data(self, count: int, what: str) -> np.ndarray:
        """``count`` stored values, decoded with the grid's codec."""
        if count == 0 and self.half:
            return np.zeros(0, self.stored)  # half-float writers emit nothing for empty arrays
        nbytes = count * self.stored.itemsize
        cur = self.cur
        if not self.compression & (_COMPRESS_BLOSC | _COMPRESS_ZIP):
            return np.frombuffer(cur.take(nbytes, what), self.stored)
        chunk = cur.i64(f"{what} chunk size")
        if chunk <= 0:
            if -chunk != nbytes:
                raise cur.error(f"corrupted file: expected {nbytes} bytes of {what} at offset "
                                f"{cur.pos - 8}, found a {-chunk}-byte chunk")
            return np.frombuffer(cur.take(nbytes, what), self.stored)
        packed = cur.take(chunk, what)
        if self.compression & _COMPRESS_BLOSC:
            raw = self._unblosc(packed, nbytes, what)
        else:
            raw = self._unzip(packed, nbytes, what)
        return np.frombuffer(raw, self.stored)

    def _unzip(self, packed: memoryview, nbytes: int, what: str) -> bytes:
        try:
            raw = zlib.decompressobj().decompress(packed, nbytes)
        except zlib.error as exc:
            raise self.cur.error(f"corrupted zip data in {what} of grid '{self.grid_name}' "
                                 f"before offset {self.cur.pos}: {exc}") from None
        if len(raw) != nbytes:
            raise self.cur.error(f"corrupted zip data in {what} of grid '{self.grid_name}' before "
                                 f"offset {self.cur.pos}: {len(raw)} bytes instead of {nbytes}")
        return raw

    def _unblosc(self, packed: memoryview, nbytes: int, what: str) -> bytes:
        try:
            import blosc
        except ImportError:
            raise self.cur.error(f"grid '{self.grid_name}' is Blosc-compressed; install the "
                                 "optional dependency with `pip install nrc[blosc]`") from None
        where = f"{what} of grid '{self.grid_name}' before offset {self.cur.pos}"
        # Blosc header: version, versionlz, flags, typesize, nbytes, blocksize, cbytes.
        if len(packed) < 16 or struct.unpack_from("<II", packed, 4)[0] != nbytes or \
                struct.unpack_from("<I", packed, 12)[0] != len(packed):
            raise self.cur.error(f"corrupted Blosc data in {where}: bad chunk header")
        try:
            raw = blosc.decompress(packed)
        except Exception as exc:  # blosc raises RuntimeError/ValueError for corrupt input
            raise self.cur.error(f"corrupted Blosc data in {where}: {exc}") from None
        if len(raw) != nbytes:
            raise self.cur.error(f"corrupted Blosc data in {where}: {len(raw)} bytes instead of "
                                 f"{nbytes}")
        return raw


def _split_offsets(offsets: np.ndarray, log2: int) -> np.ndarray:
    """Node-local linear offsets (x-major: ``x << 2 log2 | y << log2 | z``) -> (N, 3) int64 ijk."""
    offsets = offsets.astype(np.int64)
    mask = (1 << log2) - 1
    return np.stack([offsets >> (2 * log2), (offsets >> log2) & mask, offsets & mask], axis=1)


def _densify(tree: _Tree, cur: _Cursor) -> tuple[np.ndarray, tuple[int, int, int]]:
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
    blocks = blocks[occupied].reshape(-1, *(3 * (1 << _LEAF_LOG2,)))
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
    leaf = 1 << _LEAF_LOG2
    lo_pad = lo & ~(leaf - 1)
    nblocks = ((hi | (leaf - 1)) - lo_pad + 1) // leaf
    padded = np.full(tuple((nblocks * leaf).tolist()), tree.background, np.float32)
    for start, stop, value in zip((tree.tile_origins - lo_pad).tolist(),
                                  (tile_hi - lo_pad + 1).tolist(),
                                  tree.tile_values.tolist()):
        padded[start[0]:stop[0], start[1]:stop[1], start[2]:stop[2]] = value
    as_blocks = padded.reshape(nblocks[0], leaf, nblocks[1], leaf, nblocks[2], leaf)
    index = (origins - lo_pad) >> _LEAF_LOG2
    as_blocks.transpose(0, 2, 4, 1, 3, 5)[index[:, 0], index[:, 1], index[:, 2]] = blocks
    begin, end = lo - lo_pad, hi - lo_pad + 1
    values = np.ascontiguousarray(padded[begin[0]:end[0], begin[1]:end[1], begin[2]:end[2]])
    return values, (int(lo[0]), int(lo[1]), int(lo[2]))


def _leaf_bounds(origins: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-leaf inclusive index bounds ``(lo, hi)``, each (L, 3), of the active voxels."""
    side = 1 << _LEAF_LOG2
    cubes = masks.reshape(-1, side, side, side)
    lo = np.empty_like(origins)
    hi = np.empty_like(origins)
    for axis in range(3):
        others = tuple(a for a in (1, 2, 3) if a != axis + 1)
        occupied = cubes.any(axis=others)  # (L, side)
        lo[:, axis] = occupied.argmax(axis=1)
        hi[:, axis] = side - 1 - occupied[:, ::-1].argmax(axis=1)
    return origins + lo, origins + hi
