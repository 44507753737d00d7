"""Renderers selected by name (``renderer.name`` in the config), like Mitsuba's plugins."""

from __future__ import annotations

import importlib
from typing import Any

from nrc.errors import ConfigError

# name -> ("module:class" of the renderer, "module:class" of its settings); imported on demand so that start-up
# loads only the renderer in use. The settings' ``from_config(cfg.renderer)`` validates every key.
RENDERERS: dict[str, tuple[str, str]] = {
    "preview": ("nrc.render.preview:PreviewRenderer", "nrc.render.preview:PreviewSettings"),
    "pt": ("nrc.render.pt:PathTracer", "nrc.render.pt:PathTracerSettings"),
    "nrc": ("nrc.render.radiance_caching:NRCRenderer", "nrc.render.radiance_caching.settings:NRCSettings"),
}


def _load(name: Any, which: int) -> Any:
    if name not in RENDERERS:
        raise ConfigError(f"renderer.name must be one of {', '.join(sorted(RENDERERS))}, got {name!r}")
    module, cls = RENDERERS[name][which].split(":")
    return getattr(importlib.import_module(module), cls)


def make_renderer(name: str, *args: Any, **kwargs: Any) -> Any:
    """Instantiate the renderer registered as ``name``."""
    return _load(name, 0)(*args, **kwargs)


def check_settings(name: Any, renderer_cfg: Any) -> Any:
    """The renderer's validated settings, without building anything (raises ``ConfigError`` naming the key)."""
    return _load(name, 1).from_config(renderer_cfg)
