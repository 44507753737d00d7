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


# name -> "module:class" of the renderer's settings (``from_config(cfg.renderer)`` validates every key)
SETTINGS: dict[str, str] = {
    "preview": "nrc.render.preview:PreviewSettings",
    "pt": "nrc.render.pt:PathTracerSettings",
    "nrc": "nrc.render.radiance_caching.settings:NRCSettings",
}


def check_settings(name: Any, renderer_cfg: Any) -> Any:
    """The renderer's validated settings, without building anything (raises ``ConfigError`` naming the key)."""
    if name not in SETTINGS:
        raise ConfigError(f"renderer.name must be one of {', '.join(sorted(SETTINGS))}, got {name!r}")
    module, cls = SETTINGS[name].split(":")
    return getattr(importlib.import_module(module), cls).from_config(renderer_cfg)
