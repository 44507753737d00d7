"""nrc: neural radiance caching for heterogeneous participating media, in pure PyTorch.

From Python (:mod:`nrc.api`; ``import nrc`` itself loads no torch)::

    import nrc
    r = nrc.run(["scene=thick", "renderer=pt"])           # r.image, r.denoised, r.metrics, r.config
    for f in nrc.frames({"frames": 30}):                  # NRC frame by frame
        ...

Errors are :class:`nrc.NRCError` (``nrc.errors``), naming the key or file that is wrong.
"""

from __future__ import annotations

from typing import Any

from nrc.errors import ConfigError, NRCError

__version__ = "0.1.0"
__all__ = ["ConfigError", "Frame", "NRCError", "Render", "frames", "load_config", "run"]


def __getattr__(name: str) -> Any:
    """The API of :mod:`nrc.api`, imported on first use."""
    if name in ("Frame", "Render", "frames", "load_config", "run"):
        from nrc import api

        return getattr(api, name)
    raise AttributeError(f"module 'nrc' has no attribute {name!r}")
