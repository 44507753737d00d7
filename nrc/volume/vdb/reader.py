"""The OpenVDB file: header, grid table, metadata and transforms, and the package's public reads
(:func:`read_vdb`, :func:`read_vdb_grid`, :func:`list_vdb_grids`; conventions in :mod:`nrc.volume.vdb`)."""

from __future__ import annotations

from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from nrc.errors import VDBError
from nrc.volume.vdb.codecs import COMPRESS_ACTIVE_MASK, COMPRESS_ALL, COMPRESS_ZIP
from nrc.volume.vdb.dense import densify
from nrc.volume.vdb.stream import Cursor
from nrc.volume.vdb.tree import NODE_MASK_COMPRESSION, Tree, TreeReader

__all__ = ["VDBGrid", "list_vdb_grids", "read_vdb", "read_vdb_grid"]

_MAGIC = 0x56444220  # "VDB " as a little-endian int64
_MIN_VERSION = 220  # OPENVDB_FILE_VERSION_SELECTIVE_COMPRESSION
_MAX_VERSION = 224  # OPENVDB_FILE_VERSION_MULTIPASS_IO, the current version
_FLOAT_FRUSTUM_BBOX = 221  # from this version on, frustum maps store a float bounding box

_HALF_SUFFIX = "_HalfFloat"
_NAME_SEPARATOR = "\x1e"  # unique grid names are "name<SEP>index" when names repeat
_VALUE_TYPES = {"Tree_float_5_4_3": np.dtype("<f4")}  # supported grid type -> value dtype

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
    cur: Cursor
    version: int
    compression: int  # file-wide codec flags, used only by versions before 222
    grids: list[_GridDescriptor]


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
    values, origin = densify(tree, vdb.cur)
    return VDBGrid(gd.name, values, origin, tree.background)


def _open(path: str | PathLike[str]) -> _File:
    """Read the header, the file metadata and the grid table of ``path``."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise VDBError(f"{path}: cannot read OpenVDB file: {exc.strerror or exc}") from exc
    cur = Cursor(data, str(path))
    if len(data) < 8 or cur.i64("magic number") != _MAGIC:
        raise cur.error("not an OpenVDB file (bad magic number)")
    version = cur.u32("file format version")
    if not _MIN_VERSION <= version <= _MAX_VERSION:
        raise cur.error(f"unsupported OpenVDB file format version {version} "
                        f"(supported: {_MIN_VERSION}-{_MAX_VERSION})")
    cur.take(8, "library version")
    if cur.u8("grid-offsets flag") == 0:
        raise cur.error("unsupported file: written as a stream without grid offsets")
    compression = COMPRESS_ZIP | COMPRESS_ACTIVE_MASK
    if version < NODE_MASK_COMPRESSION:
        compression = COMPRESS_ZIP if cur.u8("compression flag") else 0
    cur.take(36, "file UUID")
    _read_metadata(cur, "file metadata")
    return _File(cur, version, compression, _read_grid_table(cur))


def _read_metadata(cur: Cursor, what: str) -> dict[str, tuple[str, memoryview]]:
    """A metadata table: name -> (type name, raw value bytes)."""
    entries = {}
    for _ in range(cur.u32(f"{what} count")):
        name = cur.string(f"{what} name")
        type_name = cur.string(f"type of {what} '{name}'")
        size = cur.u32(f"size of {what} '{name}'")
        entries[name] = (type_name, cur.take(size, f"{what} '{name}'"))
    return entries


def _read_grid_table(cur: Cursor) -> list[_GridDescriptor]:
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


def _read_tree(vdb: _File, gd: _GridDescriptor) -> Tree:
    """Parse a grid's compression flags, metadata, transform, topology and leaf buffers."""
    cur = vdb.cur
    if gd.parent:
        parents = [p for p in vdb.grids if p.unique_name == gd.parent and not p.parent]
        if not parents:
            raise cur.error(f"grid '{gd.name}' is an instance of missing grid '{gd.parent}'")
        return _read_tree(vdb, parents[0])
    cur.seek(gd.grid_pos, f"start of grid '{gd.name}'")
    compression = vdb.compression
    if vdb.version >= NODE_MASK_COMPRESSION:
        compression = cur.u32(f"compression flags of grid '{gd.name}'")
    if compression & ~COMPRESS_ALL:
        raise cur.error(f"unsupported compression flags {compression:#x} in grid '{gd.name}'")
    metadata = _read_metadata(cur, f"metadata of grid '{gd.name}'")
    half_meta = metadata.get("is_saved_as_half_float")
    half = gd.half_suffix or (half_meta is not None and half_meta[0] == "bool"
                              and any(bytes(half_meta[1])))
    _skip_transform(cur, vdb.version, gd.name)
    reader = TreeReader(cur, vdb.version, compression, _VALUE_TYPES[gd.type_name], half, gd.name)
    return reader.read(gd.block_pos)


def _skip_transform(cur: Cursor, version: int, grid_name: str) -> None:
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
