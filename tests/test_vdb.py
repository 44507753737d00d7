"""Tests of the pure-numpy OpenVDB reader (``nrc.volume.vdb``).

The small files in ``tests/data`` and their expected arrays (``.npz``, made by OpenVDB's own
``copyToArray``) come from ``scripts/make_test_vdbs.py``; see its docstring for what each contains.
"""

from __future__ import annotations

import random
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from nrc.errors import VDBError
from nrc.volume.vdb import list_vdb_grids, read_vdb, read_vdb_grid

DATA = Path(__file__).resolve().parent / "data"
EXPECTED = sorted(DATA.glob("*.npz"))
SCATTERED = ["scattered_blosc", "scattered_zip", "scattered_none", "scattered_v221_zip"]
HALF = ["half_blosc", "half_zip", "half_v221_zip"]
FLOAT_TREE = b"Tree_float_5_4_3"


def vdb_path(stem: str) -> Path:
    return DATA / f"{stem}.vdb"


def expected(stem: str, grid: str = "density") -> np.ndarray:
    return np.load(DATA / f"{stem}.npz")[grid]


def grid_offsets(data: bytes) -> tuple[int, int, int, int]:
    """(table position, grid_pos, block_pos, end_pos) of the first float grid of a file."""
    type_at = data.index(FLOAT_TREE) - 4  # length-prefixed type name, maybe with a half suffix
    at = type_at + 4 + struct.unpack_from("<I", data, type_at)[0] + 4  # empty instance parent
    return (at, *struct.unpack_from("<qqq", data, at))


def write(tmp_path: Path, data: bytes | bytearray) -> Path:
    path = tmp_path / "broken.vdb"
    path.write_bytes(bytes(data))
    return path


# ------------------------------------------------------------------------------------------------
# Reading


def test_shared_cloud(shared_vdb: Path) -> None:
    assert list_vdb_grids(shared_vdb) == [("density", "Tree_float_5_4_3")]
    grid = read_vdb_grid(shared_vdb)
    assert grid.name == "density"
    assert grid.origin == (-66, -21, -90)
    assert tuple(np.add(grid.origin, grid.values.shape) - 1) == (59, 64, 63)
    density = grid.values
    assert density.shape == (126, 86, 154)
    assert density.dtype == np.float32
    assert density.min() == 0.0 and density.max() <= 1.0
    assert np.count_nonzero(density) == 363_037
    assert density.sum(dtype=np.float64) == pytest.approx(188_542.10, abs=0.01)
    np.testing.assert_array_equal(read_vdb(shared_vdb, "density"), density)


@pytest.mark.parametrize("npz", EXPECTED, ids=lambda p: p.stem)
def test_matches_openvdb(npz: Path) -> None:
    """Every float grid reads exactly as OpenVDB densifies it; ``grid=None`` is the first one."""
    arrays = np.load(npz)
    path = npz.with_suffix(".vdb")
    for name in arrays.files:
        values = read_vdb(path, name)
        assert values.dtype == np.float32
        assert values.shape == arrays[name].shape
        np.testing.assert_array_equal(values, arrays[name])
    np.testing.assert_array_equal(read_vdb(path), arrays[arrays.files[0]])


@pytest.mark.parametrize("stem", SCATTERED[1:] + HALF)
def test_codecs_and_versions_agree(stem: str) -> None:
    reference = expected(SCATTERED[0])
    if stem.startswith("half"):
        reference = reference.astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(read_vdb(vdb_path(stem)), reference)


def test_scattered_grid_layout() -> None:
    """The asymmetric test grid: its box, background fill and a few known voxels."""
    grid = read_vdb_grid(vdb_path("scattered_zip"))
    assert grid.origin == (-128, -72, -97)
    assert grid.values.shape == (72, 23, 41)
    assert grid.background == 0.25

    def at(i: int, j: int, k: int) -> float:
        return float(grid.values[i + 128, j + 72, k + 97])

    assert at(-125, -59, -97) == np.float32(0.9)  # lone voxel
    assert at(-128, -72, -88) == np.float32(0.6)  # active 8^3 tile
    assert at(-121, -65, -81) == np.float32(0.6)
    assert grid.origin[1] + grid.values.shape[1] - 1 < -47  # a leaf with only inactive voxels
    assert np.all(grid.values[64:72, 0:8, 25:33] >= 0.3)  # the fully active leaf
    assert not np.isin(grid.values, [-0.25, 3.0, 5.0, 7.0, 9.0]).any()  # no inactive value leaks


def test_half_float_storage() -> None:
    values = read_vdb(vdb_path("half_blosc"))
    full = expected("scattered_blosc")
    assert not np.array_equal(values, full)
    np.testing.assert_array_equal(values, full.astype(np.float16).astype(np.float32))


def test_tiles() -> None:
    grid = read_vdb_grid(vdb_path("tiles_blosc"))
    values = grid.values
    assert grid.origin == (0, 0, 0)
    assert values.shape == (136, 130, 132)
    assert np.all(values[:128, :128, :128] == 0.5)  # 128^3 tile
    assert np.all(values[128:136, 8:16, 0:8] == 0.75)  # 8^3 tile
    assert values[130, 2, 100] == np.float32(0.1)
    assert values[5, 129, 7] == np.float32(0.2)
    assert values[64, 20, 131] == np.float32(0.3)
    inactive_tile = values[:128, 128:130, :128].copy()  # inactive 128^3 tile of value 2
    inactive_tile[5, 1, 7] = 0.0
    assert not inactive_tile.any()
    assert np.count_nonzero(values) == 128**3 + 8**3 + 3


def test_active_root_tile_is_too_large() -> None:
    with pytest.raises(VDBError, match=r"root_tile_blosc\.vdb: active bounding box .* too large"):
        read_vdb(vdb_path("root_tile_blosc"))


def test_several_grids_and_instances() -> None:
    path = vdb_path("multi_blosc")
    assert list_vdb_grids(path) == [
        ("velocity", "Tree_vec3s_5_4_3"),
        ("density", "Tree_float_5_4_3"),
        ("temperature", "Tree_float_5_4_3"),
        ("density_instance", "Tree_float_5_4_3"),
    ]
    density = read_vdb(path)  # skips the leading Vec3S grid
    np.testing.assert_array_equal(density, read_vdb(path, "density"))
    np.testing.assert_array_equal(density, read_vdb(path, "density_instance"))
    assert read_vdb_grid(path, "temperature").values.max() == 310.5
    with pytest.raises(VDBError, match=r"'velocity' has unsupported type Tree_vec3s_5_4_3"):
        read_vdb(path, "velocity")
    with pytest.raises(VDBError, match=r"no grid named 'pressure'; grids: 'velocity' .*'density'"
                                       r" .*'temperature' .*'density_instance'"):
        read_vdb(path, "pressure")


def test_blosc_is_optional(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "blosc", None)  # makes `import blosc` fail
    with pytest.raises(VDBError, match=r"Blosc-compressed; .*pip install nrc\[blosc\]"):
        read_vdb(vdb_path("scattered_blosc"))
    np.testing.assert_array_equal(read_vdb(vdb_path("scattered_zip")), expected("scattered_zip"))


# ------------------------------------------------------------------------------------------------
# Malformed files


def test_missing_and_empty_files(tmp_path: Path) -> None:
    with pytest.raises(VDBError, match="cannot read"):
        read_vdb(tmp_path / "absent.vdb")
    with pytest.raises(VDBError, match="not an OpenVDB file"):
        read_vdb(write(tmp_path, b""))


def test_bad_magic(tmp_path: Path) -> None:
    data = bytearray(vdb_path("scattered_zip").read_bytes())
    data[:4] = b"NVDB"
    with pytest.raises(VDBError, match=r"broken\.vdb: not an OpenVDB file \(bad magic number\)"):
        read_vdb(write(tmp_path, data))


@pytest.mark.parametrize("version", [219, 225])
def test_unsupported_version(tmp_path: Path, version: int) -> None:
    data = bytearray(vdb_path("scattered_zip").read_bytes())
    struct.pack_into("<I", data, 8, version)
    with pytest.raises(VDBError, match=f"unsupported OpenVDB file format version {version}"):
        read_vdb(write(tmp_path, data))


def test_unknown_grid_type(tmp_path: Path) -> None:
    path = write(tmp_path, vdb_path("scattered_zip").read_bytes().replace(FLOAT_TREE,
                                                                          b"Tree_fl0at_5_4_3"))
    assert list_vdb_grids(path) == [("density", "Tree_fl0at_5_4_3")]
    with pytest.raises(VDBError, match=r"no float grid in the file; grids: 'density' "
                                       r"\(Tree_fl0at_5_4_3\)"):
        read_vdb(path)
    with pytest.raises(VDBError, match=r"grid 'density' has unsupported type Tree_fl0at_5_4_3"):
        read_vdb(path, "density")


@pytest.mark.parametrize("stem", SCATTERED + ["half_blosc", "tiles_blosc"])
def test_truncated_files(tmp_path: Path, stem: str) -> None:
    """Cuts in the header, the grid table and the tree data (with the table patched to match)."""
    data = vdb_path(stem).read_bytes()
    table, grid_pos, block_pos, end_pos = grid_offsets(data)
    for cut in (12, 20, 40, 60, table - 20, table - 4, table + 10):
        with pytest.raises(VDBError, match="broken.vdb: truncated"):
            read_vdb(write(tmp_path, data[:cut]))
    for cut in (grid_pos + 2, grid_pos + 200, block_pos - 3, block_pos + 1, block_pos + 70,
                (block_pos + end_pos) // 2, end_pos - 1):
        truncated = bytearray(data[:cut])
        struct.pack_into("<q", truncated, table + 16, cut)  # end of the grid
        with pytest.raises(VDBError, match="broken.vdb: truncated"):
            read_vdb(write(tmp_path, truncated))


def test_grid_table_outside_file(tmp_path: Path) -> None:
    data = bytearray(vdb_path("scattered_none").read_bytes())
    table = grid_offsets(data)[0]
    struct.pack_into("<q", data, table + 16, len(data) + 100)
    with pytest.raises(VDBError, match="grid 'density' has invalid offsets"):
        read_vdb(write(tmp_path, data))


def test_garbage_zip_data(tmp_path: Path) -> None:
    data = bytearray(vdb_path("scattered_zip").read_bytes())
    chunk = data.index(b"\x78\x9c", grid_offsets(data)[2])  # first zlib stream in the leaves
    data[chunk + 2:chunk + 12] = b"\xff" * 10
    with pytest.raises(VDBError, match="corrupted zip data in leaf values of grid 'density'"):
        read_vdb(write(tmp_path, data))


def blosc_chunks(data: bytes, start: int) -> list[tuple[int, int]]:
    """(position, size) of the Blosc chunks after ``start``, found by their headers."""
    chunks = []
    for pos in range(start, len(data) - 24):
        size = struct.unpack_from("<q", data, pos)[0]
        if 16 < size < 1 << 20 and struct.unpack_from("<I", data, pos + 20)[0] == size:
            chunks.append((pos + 8, size))
    return chunks


def test_garbage_blosc_data(tmp_path: Path) -> None:
    data = bytes(vdb_path("scattered_blosc").read_bytes())
    chunks = blosc_chunks(data, grid_offsets(data)[2])
    pos, size = next((p, n) for p, n in chunks if not data[p + 2] & 0x2)  # a compressed chunk
    garbage = bytearray(data)
    garbage[pos + 16:pos + size] = bytes((37 * i + 7) % 256 for i in range(size - 16))
    with pytest.raises(VDBError, match="corrupted Blosc data in leaf values"):
        read_vdb(write(tmp_path, garbage))
    bad_header = bytearray(data)
    struct.pack_into("<I", bad_header, pos + 4, 12345)  # uncompressed size
    with pytest.raises(VDBError, match="corrupted Blosc data in leaf values .*bad chunk header"):
        read_vdb(write(tmp_path, bad_header))


def test_wrong_raw_chunk_size(tmp_path: Path) -> None:
    data = bytearray(vdb_path("scattered_zip").read_bytes())
    block_pos = grid_offsets(data)[2]
    assert data[block_pos + 64] == 0  # first leaf: value mask, metadata 0, then the chunk size
    pos = block_pos + 64 + 1
    size = struct.unpack_from("<q", data, pos)[0]
    struct.pack_into("<q", data, pos, -abs(size) - 4)
    with pytest.raises(VDBError, match="corrupted file: expected .* bytes of leaf values"):
        read_vdb(write(tmp_path, data))


def test_unknown_node_compression_metadata(tmp_path: Path) -> None:
    data = bytearray(vdb_path("scattered_none").read_bytes())
    data[grid_offsets(data)[2] + 64] = 9  # first leaf's compression metadata
    with pytest.raises(VDBError, match="unknown node compression metadata 9"):
        read_vdb(write(tmp_path, data))


@pytest.mark.parametrize("stem", ["scattered_none", "scattered_zip", "scattered_blosc",
                                  "tiles_blosc", "multi_blosc"])
def test_random_corruption_raises_only_vdb_errors(tmp_path: Path, stem: str) -> None:
    """Flipped bits, overwritten words, cuts: each file reads or raises VDBError, nothing else."""
    data = vdb_path(stem).read_bytes()
    rng = random.Random(stem)
    for _ in range(60):
        broken = bytearray(data)
        pos = rng.randrange(len(data))
        kind = rng.randrange(3)
        if kind == 0:
            broken[pos] ^= 1 << rng.randrange(8)
        elif kind == 1:
            broken[pos:pos + 8] = rng.randbytes(8)
        else:
            del broken[pos:]
        try:
            read_vdb(write(tmp_path, broken))
        except VDBError:
            pass
