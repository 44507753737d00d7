#!/usr/bin/python3
"""Generate the small OpenVDB test files of ``tests/data/`` (for ``tests/test_vdb.py``).

Usage (Debian's *system* Python, which has the OpenVDB 10 bindings; not the project venv)::

    apt-get install python3-openvdb python3-numpy    # libblosc1 comes with it
    /usr/bin/python3 scripts/make_test_vdbs.py [OUTPUT_DIR]    # default: tests/data

Every ``NAME.vdb`` comes with ``NAME.npz``: one expected dense float32 array per float grid, keyed
by grid name in file order, over the grid's active index bounding box, with inactive voxels at the
background value (the convention of ``nrc.volume.vdb.read_vdb``). The arrays come from OpenVDB
itself: each written file is read back with pyopenvdb and densified with ``copyToArray``.

Files (``*_blosc`` are written by pyopenvdb, which always uses Blosc + active-mask compression):

* ``scattered_{blosc,zip,none}.vdb``: one float grid ``density`` (background 0.25) with scattered
  leaves in an asymmetric pattern, built so that the leaves use every per-node mask-compression
  scheme (0-6), plus a fully active leaf, a leaf without active voxels and an active 8^3 tile.
* ``scattered_v221_zip.vdb``: the same grid in the older format 221 (file-wide zip flag, no per-node
  compression metadata, leaf origins in the data blocks).
* ``half_{blosc,zip,v221_zip}.vdb``: that grid saved as half floats.
* ``tiles_blosc.vdb``: a fog grid (background 0) with an active 128^3 tile, an active 8^3 tile and
  voxels, an inactive 128^3 tile and an inactive root (4096^3) tile.
* ``root_tile_blosc.vdb``: an active 4096^3 root tile (too large to densify; no ``.npz``).
* ``multi_blosc.vdb``: a Vec3S grid ``velocity`` first, then float grids ``density`` and
  ``temperature`` and ``density_instance``, an instance sharing the tree of ``density``.

The zip, uncompressed and format-221 variants are made by re-encoding the pyopenvdb output with the
small transcoder below (the bindings cannot choose a codec); each variant is checked by reading it
back with OpenVDB and comparing it to the original, voxel for voxel.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pyopenvdb as vdb

COMPRESS_ZIP, COMPRESS_ACTIVE_MASK, COMPRESS_BLOSC = 0x1, 0x2, 0x4
INACTIVE_VALUES_STORED = {2: 1, 4: 1, 5: 2}  # per-node compression scheme -> explicit values
SELECTION_MASK_STORED = (3, 4, 5)
NO_MASK_AND_ALL_VALS = 6
MAP_SIZES = {"UniformScaleMap": 120, "ScaleMap": 120, "UniformScaleTranslateMap": 144,
             "ScaleTranslateMap": 144, "TranslationMap": 24, "AffineMap": 128, "UnitaryMap": 128}
DROPPED_METADATA = ("file_delayed_load", "file_compression")  # stale after re-encoding
LEGACY_VERSION = 221

_BLOSC = ctypes.CDLL(ctypes.util.find_library("blosc") or "libblosc.so.1")
_BLOSC.blosc_decompress.argtypes = [ctypes.c_char_p, ctypes.c_void_p, ctypes.c_size_t]


# ------------------------------------------------------------------------------------------------
# Grids


def scattered_grid(name: str, half: bool) -> vdb.FloatGrid:
    """Background 0.25; one leaf per mask-compression scheme, a full and an empty leaf, a tile.

    Everything lies in one 128^3 internal node of the negative octant, to keep the file small.
    """
    rng = np.random.default_rng(7)
    bg = 0.25
    grid = vdb.FloatGrid(bg)
    grid.name = name
    grid.saveFloatAsHalf = half
    acc = grid.getAccessor()

    def activate(origin: tuple[int, int, int], n: int) -> None:
        for ijk in rng.integers(0, 8, size=(n, 3)):
            value = float(rng.uniform(0.3, 1))
            acc.setValueOn(tuple(int(o + d) for o, d in zip(origin, ijk)), value)

    def deactivate(origin: tuple[int, int, int], value: float, n: int) -> None:
        for ijk in rng.integers(0, 8, size=(n, 3)):
            acc.setValueOff(tuple(int(o + d) for o, d in zip(origin, ijk)), value)

    def fill_leaf_inactive(origin: tuple[int, int, int], value: float) -> None:
        grid.fill(origin, tuple(o + 7 for o in origin), value, False)

    activate((-104, -64, -88), 9)  # scheme 0: inactive voxels are the background
    fill_leaf_inactive((-96, -64, -88), -bg)  # scheme 1: inactive voxels are -background
    activate((-96, -64, -88), 5)
    fill_leaf_inactive((-88, -72, -80), 5.0)  # scheme 2: one other inactive value
    activate((-88, -72, -80), 6)
    activate((-120, -64, -72), 4)  # scheme 3: mask selects background / -background
    deactivate((-120, -64, -72), -bg, 5)
    activate((-80, -56, -88), 7)  # scheme 4: mask selects background / one other value
    deactivate((-80, -56, -88), 7.0, 6)
    fill_leaf_inactive((-72, -64, -96), 7.0)  # scheme 5: mask selects two other values
    deactivate((-72, -64, -96), 9.0, 4)
    activate((-72, -64, -96), 3)
    activate((-112, -56, -64), 5)  # scheme 6: three distinct inactive values, all stored
    deactivate((-112, -56, -64), 7.0, 3)
    deactivate((-112, -56, -64), 9.0, 3)
    grid.copyFromArray(rng.uniform(0.3, 1, size=(8, 8, 8)).astype(np.float32), (-64, -72, -72))
    acc.setValueOff((-54, -47, -53), 3.0)  # a leaf without active voxels
    grid.fill((-128, -72, -88), (-121, -65, -81), 0.6)  # an active 8^3 tile
    acc.setValueOn((-125, -59, -97), 0.9)
    return grid


def tiles_grid() -> vdb.FloatGrid:
    """A fog grid with active tiles at both internal levels, inactive tiles and some voxels."""
    grid = vdb.FloatGrid(0.0)
    grid.name = "density"
    grid.fill((0, 0, 0), (127, 127, 127), 0.5)  # level-2 tile
    grid.fill((128, 8, 0), (135, 15, 7), 0.75)  # level-1 tile
    grid.fill((0, 128, 0), (127, 255, 127), 2.0, False)  # inactive level-2 tile
    grid.fill((-4096, 0, 0), (-1, 4095, 4095), 0.3, False)  # inactive root tile
    acc = grid.getAccessor()
    for ijk, value in (((130, 2, 100), 0.1), ((5, 129, 7), 0.2), ((64, 20, 131), 0.3)):
        acc.setValueOn(ijk, value)
    return grid


def root_tile_grid() -> vdb.FloatGrid:
    grid = vdb.FloatGrid(0.0)
    grid.name = "density"
    grid.fill((0, 0, 0), (4095, 4095, 4095), 1.0)
    return grid


def multi_grids() -> list:
    """A Vec3S grid first, then two float grids and an instance of the first float grid."""
    velocity = vdb.Vec3SGrid()
    velocity.name = "velocity"
    velocity.getAccessor().setValueOn((1, 2, 3), (1.0, 2.0, 3.0))
    density = vdb.FloatGrid()
    density.name = "density"
    temperature = vdb.FloatGrid()
    temperature.name = "temperature"
    for ijk, value in (((3, 1, 4), 0.5), ((1, 5, 9), 0.25), ((2, 16, 5), 1.0)):
        density.getAccessor().setValueOn(ijk, value)
    for ijk, value in (((10, 0, 4), 300.0), ((12, 3, 0), 310.5)):
        temperature.getAccessor().setValueOn(ijk, value)
    instance = density.copy()  # shares the tree, so OpenVDB writes it as an instance
    instance.name = "density_instance"
    return [velocity, density, temperature, instance]


# ------------------------------------------------------------------------------------------------
# Transcoder


def bits(raw: bytes) -> np.ndarray:
    return np.unpackbits(np.frombuffer(raw, np.uint8), bitorder="little").astype(bool)


class Transcoder:
    """Re-encode a format-224 file written by OpenVDB with another codec, or as format 221.

    Handles what pyopenvdb writes: ``Tree_{float,vec3s}_5_4_3`` grids (half or not), linear
    transforms, instances. Positions in the grid table are recomputed.
    """

    def __init__(self, data: bytes, codec: int, legacy: bool) -> None:
        assert codec in (0, COMPRESS_ZIP)
        self.src, self.pos, self.out = data, 0, bytearray()
        self.codec, self.legacy = codec, legacy
        # State of the grid being copied, set by grid() and topology().
        self.src_codec = self.masked = self.vsize = 0
        self.half = False
        self.background = b""
        self.leaves: list[tuple[np.ndarray, np.ndarray]] = []

    def read(self, n: int) -> bytes:
        chunk = self.src[self.pos:self.pos + n]
        assert len(chunk) == n, "unexpected end of file"
        self.pos += n
        return chunk

    def copy(self, n: int) -> bytes:
        chunk = self.read(n)
        self.out += chunk
        return chunk

    def unpack(self, fmt: str, copy: bool = True) -> int:
        raw = self.copy(struct.calcsize(fmt)) if copy else self.read(struct.calcsize(fmt))
        return struct.unpack(fmt, raw)[0]

    def copy_string(self) -> str:
        return self.copy(self.unpack("<I")).decode()

    def run(self) -> bytes:
        self.copy(8)  # magic
        version = self.unpack("<I", copy=False)
        assert version == 224
        self.out += struct.pack("<I", LEGACY_VERSION if self.legacy else version)
        self.copy(9)  # library version, grid-offsets flag
        if self.legacy:
            self.out += bytes([self.codec == COMPRESS_ZIP])
        self.copy(36)  # UUID
        self.metadata()
        for _ in range(self.unpack("<i")):
            self.grid()
        assert self.pos == len(self.src)
        return bytes(self.out)

    def metadata(self) -> dict[str, bytes]:
        count = self.unpack("<I", copy=False)
        entries = []
        for _ in range(count):
            name = self.read(self.unpack("<I", copy=False)).decode()
            type_name = self.read(self.unpack("<I", copy=False))
            entries.append((name, type_name, self.read(self.unpack("<I", copy=False))))
        kept = [e for e in entries if e[0] not in DROPPED_METADATA]
        self.out += struct.pack("<I", len(kept))
        for name, type_name, value in kept:
            for field in (name.encode(), type_name, value):
                self.out += struct.pack("<I", len(field)) + field
        return {name: value for name, _, value in entries}

    def grid(self) -> None:
        self.copy_string()  # unique name
        type_name = self.copy_string()
        parent = self.copy_string()
        table_at = len(self.out)
        _, _, src_end = struct.unpack("<qqq", self.read(24))
        self.out += bytes(24)
        grid_pos = len(self.out)
        flags = self.unpack("<I", copy=False)
        self.src_codec = flags & (COMPRESS_ZIP | COMPRESS_BLOSC)
        self.masked = flags & COMPRESS_ACTIVE_MASK
        if not self.legacy:
            self.out += struct.pack("<I", self.codec | self.masked)
        meta = self.metadata()
        self.half = (type_name.endswith("_HalfFloat")
                     or meta.get("is_saved_as_half_float") == b"\x01")
        self.vsize = 12 if "vec3s" in type_name else 4
        self.copy(MAP_SIZES[self.copy_string()])  # transform
        block_pos = 0
        if not parent:
            self.leaves = []
            self.topology()
            block_pos = len(self.out)
            for origin, mask in self.leaves:
                self.copy(64)
                if self.legacy:
                    self.out += struct.pack("<3ib", *origin.tolist(), 1)
                self.values(512, mask)
        assert self.pos == src_end
        struct.pack_into("<qqq", self.out, table_at, grid_pos, block_pos, len(self.out))

    def topology(self) -> None:
        assert self.unpack("<i") == 1  # buffer count
        self.background = self.copy(self.vsize)
        num_tiles, num_children = self.unpack("<I"), self.unpack("<I")
        self.copy(num_tiles * (12 + self.vsize + 1))
        for _ in range(num_children):
            self.internal(np.array(struct.unpack("<3i", self.copy(12))), 0)

    def internal(self, origin: np.ndarray, level: int) -> None:
        log2, child_log2 = (5, 4)[level], (7, 3)[level]
        size = 1 << (3 * log2)
        child, value = bits(self.copy(size // 8)), bits(self.copy(size // 8))
        self.values(size, value, None if not self.legacy else ~child)
        offsets = np.flatnonzero(child)
        ijk = np.stack([offsets >> 2 * log2, (offsets >> log2) & ((1 << log2) - 1),
                        offsets & ((1 << log2) - 1)], axis=1)
        for child_origin in origin + (ijk << child_log2):
            if level == 0:
                self.internal(child_origin, 1)
            else:
                self.leaves.append((child_origin, bits(self.copy(64))))

    def values(self, size: int, active: np.ndarray, slots: np.ndarray | None = None) -> None:
        """One node's value array: copy or expand its compression metadata, re-encode its data."""
        scheme = self.read(1)[0]
        inactive = [self.read(self.vsize) for _ in range(INACTIVE_VALUES_STORED.get(scheme, 0))]
        selection_raw = self.read(size // 8) if scheme in SELECTION_MASK_STORED else b""
        count = int(active.sum()) if self.masked and scheme != NO_MASK_AND_ALL_VALS else size
        esize = self.vsize // 2 if self.half else self.vsize
        data = self.decode(count * esize, count)
        if not self.legacy:
            self.out += bytes([scheme]) + b"".join(inactive) + selection_raw
            self.out += self.encode(data, count)
            return
        rows = np.frombuffer(data, np.uint8).reshape(count, esize)
        if count != size:  # restore the inactive values, as OpenVDB's reader does
            background = np.frombuffer(self.background, "<f4")
            val0 = background if scheme == 0 else -background
            val0 = np.frombuffer(inactive[0], "<f4") if inactive else val0
            val1 = np.frombuffer(inactive[1], "<f4") if len(inactive) == 2 else background
            selection = bits(selection_raw) if selection_raw else np.zeros(size, bool)
            full = np.empty((size, esize), np.uint8)
            full[active] = rows
            for chosen, val in ((selection, val1), (~selection, val0)):
                stored = val.astype("<f2") if self.half else val
                full[~active & chosen] = np.frombuffer(stored.tobytes(), np.uint8)
            rows = full
        if slots is not None:
            rows = rows[slots]
        self.out += self.encode(rows.tobytes(), len(rows))

    def decode(self, nbytes: int, count: int) -> bytes:
        if self.half and count == 0:
            return b""
        if not self.src_codec:
            return self.read(nbytes)
        size = self.unpack("<q", copy=False)
        if size <= 0:
            return self.read(-size)
        packed = self.read(size)
        if self.src_codec & COMPRESS_BLOSC:
            raw = ctypes.create_string_buffer(nbytes)
            assert _BLOSC.blosc_decompress(packed, raw, nbytes) == nbytes
            return raw.raw
        return zlib.decompress(packed)

    def encode(self, raw: bytes, count: int) -> bytes:
        if (self.half and count == 0) or not self.codec:
            return raw
        packed = zlib.compress(raw)
        if len(packed) < len(raw):
            return struct.pack("<q", len(packed)) + packed
        return struct.pack("<q", -len(raw)) + raw


# ------------------------------------------------------------------------------------------------
# Expected arrays and verification


def expected_dense(grid) -> np.ndarray:
    """The grid over its active bounding box, inactive voxels at the background (as read_vdb)."""
    lo, hi = grid.evalActiveVoxelBoundingBox()
    shape = tuple(h - l + 1 for l, h in zip(lo, hi))
    dense = np.zeros(shape, np.float32)
    grid.copyToArray(dense, ijk=lo)
    active = np.zeros(shape, bool)
    for item in grid.citerOnValues():
        a = [m - l for m, l in zip(item["min"], lo)]
        b = [m - l + 1 for m, l in zip(item["max"], lo)]
        active[a[0]:b[0], a[1]:b[1], a[2]:b[2]] = True
    return np.where(active, dense, np.float32(grid.background))


def float_arrays(path: Path) -> dict[str, np.ndarray]:
    grids, _ = vdb.readAll(str(path))
    return {g.name: expected_dense(g) for g in grids if isinstance(g, vdb.FloatGrid)}


def same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def write(out_dir: Path, stem: str, grids: list) -> dict[str, np.ndarray]:
    path = out_dir / f"{stem}_blosc.vdb"
    vdb.write(str(path), grids)
    arrays = float_arrays(path)
    np.savez_compressed(out_dir / f"{stem}_blosc.npz", **arrays)
    return arrays


def transcode(out_dir: Path, stem: str, suffix: str, codec: int, legacy: bool,
              reference: dict[str, np.ndarray]) -> None:
    data = Transcoder((out_dir / f"{stem}_blosc.vdb").read_bytes(), codec, legacy).run()
    path = out_dir / f"{stem}_{suffix}.vdb"
    path.write_bytes(data)
    arrays = float_arrays(path)
    assert same(arrays, reference), f"{path} does not read back like the original"
    np.savez_compressed(out_dir / f"{stem}_{suffix}.npz", **arrays)


def main(out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    scattered = write(out_dir, "scattered", [scattered_grid("density", half=False)])
    half = write(out_dir, "half", [scattered_grid("density", half=True)])
    assert not np.array_equal(half["density"], scattered["density"])
    rounded = scattered["density"].astype(np.float16).astype(np.float32)
    assert np.array_equal(half["density"], rounded)
    transcode(out_dir, "scattered", "zip", COMPRESS_ZIP, False, scattered)
    transcode(out_dir, "scattered", "none", 0, False, scattered)
    transcode(out_dir, "scattered", "v221_zip", COMPRESS_ZIP, True, scattered)
    transcode(out_dir, "half", "zip", COMPRESS_ZIP, False, half)
    transcode(out_dir, "half", "v221_zip", COMPRESS_ZIP, True, half)
    write(out_dir, "tiles", [tiles_grid()])
    vdb.write(str(out_dir / "root_tile_blosc.vdb"), [root_tile_grid()])
    multi = write(out_dir, "multi", multi_grids())
    assert np.array_equal(multi["density"], multi["density_instance"])
    for path in sorted(out_dir.glob("*.vdb")):
        print(f"{path.name}: {path.stat().st_size} bytes")


if __name__ == "__main__":
    default = Path(__file__).resolve().parent.parent / "tests" / "data"
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else default)
