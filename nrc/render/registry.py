"""Renderers selected by name (``renderer.name`` in the config), like Mitsuba's plugins."""

from __future__ import annotations

import importlib
from typing import Any

from nrc.errors import ConfigError

# name -> "module:class"; imported on demand so that start-up loads only the renderer in use.
RENDERERS: dict[str, str] = {
    "preview": "nrc.render.preview:PreviewRenderer",
    "pt": "nrc.render.pt:PathTracer",
    "nrc": "nrc.render.radiance_caching:NRCRenderer",
}


def make_renderer(name: str, *args: Any, **kwargs: Any) -> Any:
    """Instantiate the renderer registered as ``name``."""
    if name not in RENDERERS:
        raise ConfigError(f"renderer.name must be one of {', '.join(sorted(RENDERERS))}, got {name!r}")
    module, cls = RENDERERS[name].split(":")
    return getattr(importlib.import_module(module), cls)(*args, **kwargs)
