"""Bounds-checked little-endian reads over an OpenVDB file's bytes (:class:`Cursor`)."""

from __future__ import annotations

import struct

import numpy as np

from nrc.errors import VDBError


class Cursor:
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
