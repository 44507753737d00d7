"""Transmittance estimators for ray segments through the density grid.

Every estimator has the signature::

    estimate(grid, majorants, origin, direction, t0, t1, gen, **params, return_stats=False) -> T (N,)

with ``origin`` ``(N, 3)``, unit ``direction`` ``(N, 3)``, segment ``[t0, t1]`` (floats, ``(N,)`` tensors or
``None`` for ``0`` / the box exit) clipped to the density box, and all randomness from ``gen``. With
``return_stats=True`` it returns ``(T, TrackingStats)`` (lookup counts). See ``docs/transmittance.md`` for the
measured variance and cost of each.

========================  ===================================================  ======================
name                      estimator                                            range
========================  ===================================================  ======================
``ratio``                 ratio tracking (global / brick majorant, roulette)    ``[0, 1]``
``residual_ratio``        residual ratio tracking, per-brick controls           ``>= 0``
``track_length``          delta tracking as a binary estimator                 ``{0, 1}``
``unbiased_raymarch``     Kettunen et al. 2021                                 any real (unclamped)
``biased_raymarch``       the comb only, ``exp(-X)`` (biased upwards)          ``[0, 1]``
========================  ===================================================  ======================

A new estimator is one file and one YAML: a module with a function of the signature above (its keyword
parameters with defaults are the tunable ones) and ``conf/transmittance/<name>.yaml`` naming it::

    name: my_estimator
    estimator: my_package.my_module:estimate   # imported and registered under ``name`` on first use
    my_param: 0.5

(or :func:`register` in code). Estimators without a per-step form run on the queued shadow rays of
``pt`` and ``nrc`` (``renderer.shadow_batch`` rays a call).
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Mapping
from typing import Any

from nrc.errors import ConfigError
from nrc.transport.tracking import TrackingStats
from nrc.transport.transmittance import biased_raymarch, ratio, residual_ratio, track_length, unbiased_raymarch
from nrc.transport.transmittance.unbiased_raymarch import roulette_probabilities

ESTIMATORS: dict[str, Callable[..., Any]] = {
    "ratio": ratio.estimate,
    "residual_ratio": residual_ratio.estimate,
    "track_length": track_length.estimate,
    "unbiased_raymarch": unbiased_raymarch.estimate,
    "biased_raymarch": biased_raymarch.estimate,
}

# The estimator the path tracer should use for shadow rays unless configured otherwise (docs/transmittance.md).
DEFAULT_ESTIMATOR = "ratio"

_POSITIONAL = ("grid", "majorants", "origin", "direction", "t0", "t1", "gen", "return_stats")


def register(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    """Register estimator ``fn`` under ``name`` (the signature in the module docstring); returns ``fn``.

    Raises:
        ConfigError: ``name`` already names another estimator, or ``fn`` lacks the positional parameters.
    """
    if ESTIMATORS.get(name, fn) is not fn:
        raise ConfigError(f"transmittance {name!r} is already registered to another estimator")
    params = list(inspect.signature(fn).parameters)
    missing = [p for p in _POSITIONAL if p not in params]
    if missing:
        raise ConfigError(f"transmittance estimator {name!r} lacks the parameter(s) {', '.join(missing)}")
    ESTIMATORS[name] = fn
    return fn


def _load(name: str, spec: str) -> None:
    """Import ``module:function`` and register it as ``name`` (``transmittance.estimator``)."""
    module, _, attr = str(spec).partition(":")
    if not module or not attr:
        raise ConfigError(f"transmittance.estimator must be 'module:function', got {spec!r}")
    try:
        fn = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"transmittance.estimator {spec!r} cannot be imported: {exc}") from None
    register(name, fn)


def estimator_params(name: str) -> dict[str, Any]:
    """The tunable parameters of estimator ``name`` with their defaults."""
    sig = inspect.signature(ESTIMATORS[name])
    return {k: p.default for k, p in sig.parameters.items() if k not in _POSITIONAL}


class Transmittance:
    """A configured estimator: ``T = est(grid, majorants, origin, direction, t0, t1, gen)``.

    Attributes:
        name: registry name; params: the parameters passed on every call.
    """

    def __init__(self, name: str, params: Mapping[str, Any] | None = None) -> None:
        if name not in ESTIMATORS:
            raise ConfigError(f"transmittance.name must be one of {', '.join(sorted(ESTIMATORS))}, got {name!r}")
        allowed = estimator_params(name)
        params = dict(params or {})
        for key in params:
            if key not in allowed:
                raise ConfigError(
                    f"transmittance.{key} is not a parameter of {name!r} (expected one of {', '.join(allowed)})"
                )
        self.name = name
        self.params = params
        self.fn = ESTIMATORS[name]

    def __call__(self, grid, majorants, origin, direction, t0, t1, gen, return_stats: bool = False):
        return self.fn(grid, majorants, origin, direction, t0, t1, gen, return_stats=return_stats, **self.params)

    def __repr__(self) -> str:
        return f"Transmittance({self.name!r}, {self.params!r})"


def make_transmittance(cfg: Mapping[str, Any] | str | None) -> Transmittance:
    """Build the estimator described by a config section (``conf/transmittance/*.yaml``).

    Args:
        cfg: a mapping (dict or OmegaConf ``DictConfig``) with ``name`` and that estimator's parameters, a bare
            name, or ``None`` for :data:`DEFAULT_ESTIMATOR` with default parameters.

    Raises:
        ConfigError: unknown estimator name or parameter.
    """
    if cfg is None:
        return Transmittance(DEFAULT_ESTIMATOR)
    if isinstance(cfg, str):
        return Transmittance(cfg)
    items = dict(cfg.items())
    if "name" not in items:
        raise ConfigError("transmittance.name is missing")
    name = str(items.pop("name"))
    spec = items.pop("estimator", None)
    if spec is not None:
        _load(name, spec)
    return Transmittance(name, items)


__all__ = [
    "ESTIMATORS", "DEFAULT_ESTIMATOR", "Transmittance", "TrackingStats", "estimator_params",
    "make_transmittance", "register", "roulette_probabilities",
]
