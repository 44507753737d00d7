"""Renderers selected by name (``renderer.name`` in the config), like Mitsuba's plugins.

Every renderer takes the scene and its typed settings, passed whole, never the raw config (nerfstudio's typed
configs): the settings are read from the app config once (:func:`renderer_settings`: every key checked, one
``ConfigError`` naming it), their ``auto`` rules resolved for the loaded scene (:func:`resolve_settings`), then the
renderer is built (:func:`build_renderer`). :func:`make_renderer` does the three from a composed config.
"""

from __future__ import annotations

import importlib
from typing import Any

from nrc.errors import ConfigError

# name -> ("module:class" of the renderer, "module:class" of its settings); imported on demand so that start-up
# loads only the renderer in use. The settings' ``from_app_config(cfg)`` validates every key the renderer reads.
RENDERERS: dict[str, tuple[str, str]] = {
    "preview": ("nrc.render.preview:PreviewRenderer", "nrc.render.preview:PreviewSettings"),
    "pt": ("nrc.render.pt:PathTracer", "nrc.render.pt:PathTracerSettings"),
    "nrc": ("nrc.render.radiance_caching:NRCRenderer", "nrc.render.radiance_caching.settings:NRCRendererSettings"),
}


def _load(name: Any, which: int) -> Any:
    if name not in RENDERERS:
        raise ConfigError(f"renderer.name must be one of {', '.join(sorted(RENDERERS))}, got {name!r}")
    module, cls = RENDERERS[name][which].split(":")
    return getattr(importlib.import_module(module), cls)


def renderer_settings(name: Any, cfg: Any, scene: Any = None, **options: Any) -> Any:
    """The typed settings of the renderer ``name`` from the app config ``cfg`` (``ConfigError`` naming the key);
    with ``scene`` their ``auto`` rules resolved for it (:func:`resolve_settings`), the scene checked to be on
    ``cfg.device``. ``options``: the settings class's own (``own_cache=False`` for NRC with a cache of its own)."""
    settings = _load(name, 1).from_app_config(cfg, **options)
    if scene is None:
        return settings
    scene.device_for(cfg)
    return resolve_settings(settings, scene)


def resolve_settings(settings: Any, scene: Any) -> Any:
    """``settings`` with the rules that need the loaded scene resolved (``renderer=nrc``'s ``auto`` values:
    :func:`nrc.render.radiance_caching.settings.resolve_auto`); other renderers' settings as they are."""
    resolve = getattr(settings, "resolved_for", None)
    return settings if resolve is None else resolve(scene)


def build_renderer(name: Any, scene: Any, settings: Any, **kwargs: Any) -> Any:
    """The renderer ``name`` on ``scene`` with its typed settings, resolved for it (:func:`resolve_settings`;
    ``kwargs``: the renderer's own, e.g. NRC's ``cache``)."""
    return _load(name, 0)(scene, settings, **kwargs)


def make_renderer(name: str, scene: Any, cfg: Any, **kwargs: Any) -> Any:
    """The renderer ``name`` on ``scene`` configured by the app config ``cfg`` (scripts and tests): its settings
    read once and resolved (:func:`renderer_settings`), then the renderer (``kwargs``: the renderer's own, e.g.
    NRC's ``cache``, a stub the tests inject)."""
    options = {"own_cache": False} if kwargs.get("cache") is not None else {}
    return build_renderer(name, scene, renderer_settings(name, cfg, scene, **options), **kwargs)

