"""The codecs of an OpenVDB grid's value arrays: none, zip (zlib) and blosc (the optional ``blosc`` package),
chosen by the grid's compression flags (:data:`COMPRESS_ZIP`, :data:`COMPRESS_BLOSC`; :data:`COMPRESS_ACTIVE_MASK`
marks node arrays that store only their active values)."""

from __future__ import annotations

import struct
import zlib

import numpy as np

from nrc.volume.vdb.stream import Cursor

COMPRESS_ZIP = 0x1
COMPRESS_ACTIVE_MASK = 0x2
COMPRESS_BLOSC = 0x4
COMPRESS_ALL = COMPRESS_ZIP | COMPRESS_ACTIVE_MASK | COMPRESS_BLOSC


def read_data(cur: Cursor, count: int, stored: np.dtype, half: bool, compression: int, what: str,
              grid_name: str) -> np.ndarray:
    """``count`` stored values (dtype ``stored``; ``half``: half-float storage), decoded with the grid's codec."""
    if count == 0 and half:
        return np.zeros(0, stored)  # half-float writers emit nothing for empty arrays
    nbytes = count * stored.itemsize
    if not compression & (COMPRESS_BLOSC | COMPRESS_ZIP):
        return np.frombuffer(cur.take(nbytes, what), stored)
    chunk = cur.i64(f"{what} chunk size")
    if chunk <= 0:
        if -chunk != nbytes:
            raise cur.error(f"corrupted file: expected {nbytes} bytes of {what} at offset "
                            f"{cur.pos - 8}, found a {-chunk}-byte chunk")
        return np.frombuffer(cur.take(nbytes, what), stored)
    packed = cur.take(chunk, what)
    if compression & COMPRESS_BLOSC:
        raw = _unblosc(cur, packed, nbytes, what, grid_name)
    else:
        raw = _unzip(cur, packed, nbytes, what, grid_name)
    return np.frombuffer(raw, stored)


def _unzip(cur: Cursor, packed: memoryview, nbytes: int, what: str, grid_name: str) -> bytes:
    try:
        raw = zlib.decompressobj().decompress(packed, nbytes)
    except zlib.error as exc:
        raise cur.error(f"corrupted zip data in {what} of grid '{grid_name}' "
                        f"before offset {cur.pos}: {exc}") from None
    if len(raw) != nbytes:
        raise cur.error(f"corrupted zip data in {what} of grid '{grid_name}' before "
                        f"offset {cur.pos}: {len(raw)} bytes instead of {nbytes}")
    return raw


def _unblosc(cur: Cursor, packed: memoryview, nbytes: int, what: str, grid_name: str) -> bytes:
    try:
        import blosc
    except ImportError:
        raise cur.error(f"grid '{grid_name}' is Blosc-compressed; install the "
                        "optional dependency with `pip install nrc[blosc]`") from None
    where = f"{what} of grid '{grid_name}' before offset {cur.pos}"
    # Blosc header: version, versionlz, flags, typesize, nbytes, blocksize, cbytes.
    if len(packed) < 16 or struct.unpack_from("<II", packed, 4)[0] != nbytes or \
            struct.unpack_from("<I", packed, 12)[0] != len(packed):
        raise cur.error(f"corrupted Blosc data in {where}: bad chunk header")
    try:
        raw = blosc.decompress(packed)
    except Exception as exc:  # blosc raises RuntimeError/ValueError for corrupt input
        raise cur.error(f"corrupted Blosc data in {where}: {exc}") from None
    if len(raw) != nbytes:
        raise cur.error(f"corrupted Blosc data in {where}: {len(raw)} bytes instead of "
                        f"{nbytes}")
    return raw
