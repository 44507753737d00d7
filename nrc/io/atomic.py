"""Files written whole or not at all: the checkpoints, reference parts, the disk cache's arrays and the small JSON
records of sweeps and speed-versus-error jobs.

The content goes to a temporary file beside the target, named by the writing process (two processes writing the same
file never share one), and is renamed over the target only once complete: a kill mid-write leaves the previous file.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def write_atomically(path: str | Path, write: Callable[[BinaryIO], object], fsync: bool = False) -> None:
    """``write(f)`` fills ``path`` through a temporary file (its folder made first); ``fsync``: flushed to the disk
    before the rename (a checkpoint that must survive a power cut). The temporary file is removed on an error."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomically(path: str | Path, text: str) -> None:
    """:func:`write_atomically` of a UTF-8 text."""
    write_atomically(path, lambda f: f.write(text.encode()))
