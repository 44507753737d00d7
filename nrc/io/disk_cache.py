"""Arrays that are expensive to make and cheap to keep: on disk under one cache root, keyed by what makes them.

The root is ``$NRC_CACHE_DIR``, else ``$XDG_CACHE_HOME/nrc`` (``~/.cache/nrc``). An entry's key hashes its
parameters and the source files of the code that makes it (not a git revision: a wheel has none), so an edit to
that code makes new entries. Files are ``.npy``, written atomically; one that cannot be read is made again with a
warning. Set ``NRC_CACHE_DIR`` to a temporary directory for isolation (the tests do), or to ``off`` to keep nothing.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from nrc.io.atomic import write_atomically


def cache_root() -> Path | None:
    """The cache root (its folders are made when an entry is stored), or None when ``NRC_CACHE_DIR=off``."""
    given = os.environ.get("NRC_CACHE_DIR")
    if given == "off":
        return None
    if given:
        return Path(given).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nrc"


def source_hash(files: Sequence[str | Path]) -> str:
    """A short hash of the contents of ``files`` (the code that makes an entry)."""
    h = hashlib.sha1()
    for f in files:
        h.update(Path(f).read_bytes())
    return h.hexdigest()[:12]


def cached_array(kind: str, params: tuple, sources: Sequence[str | Path], make: Callable[[], np.ndarray]) -> np.ndarray:
    """``make()``'s array, from ``<root>/<kind>/<key>.npy`` when an earlier call of the same ``params`` and source
    files left it there; else made, stored and returned. A directory that cannot be written only costs the
    cache (the array is still made and returned)."""
    root = cache_root()
    if root is None:
        return make()
    key = hashlib.sha1(repr((params, source_hash(sources))).encode()).hexdigest()[:20]
    path = root / kind / f"{key}.npy"
    if path.is_file():
        try:
            return np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            warnings.warn(f"the cached {kind} {path} is unreadable ({exc}); making it again", stacklevel=2)
    array = make()
    try:
        write_atomically(path, lambda f: np.save(f, array, allow_pickle=False))
    except OSError:
        pass
    return array
