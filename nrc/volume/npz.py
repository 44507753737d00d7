"""Dense density arrays stored in NumPy ``.npz`` files (for users' own data)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from nrc.errors import ConfigError


def read_npz(path: str | Path, key: str | None = None) -> np.ndarray:
    """Read a dense ``(nx, ny, nz)`` density array from an ``.npz`` file.

    Args:
        path: the file.
        key: array name inside the file; ``None`` takes the only array (an error if there are several).

    Returns:
        float32 array ``(nx, ny, nz)``, index ``(i, j, k)`` along world ``(+x, +y, +z)``.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as f:
            names = list(f.files)
            if key is None:
                if len(names) != 1:
                    raise ConfigError(f"scene.volume.grid: {path} holds arrays {names}; name one")
                key = names[0]
            if key not in names:
                raise ConfigError(f"scene.volume.grid: no array '{key}' in {path} (it holds {names})")
            arr = np.asarray(f[key])
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"scene.volume.path: cannot read {path} as .npz ({exc})") from None
    if arr.ndim != 3 or not np.issubdtype(arr.dtype, np.number):
        raise ConfigError(f"scene.volume: array '{key}' in {path} must be a 3-D numeric array, got {arr.dtype} {arr.shape}")
    return arr.astype(np.float32)
