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
"""

from __future__ import annotations

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
    name = items.pop("name")
    return Transmittance(str(name), items)


__all__ = [
    "ESTIMATORS", "DEFAULT_ESTIMATOR", "Transmittance", "TrackingStats", "estimator_params",
    "make_transmittance", "roulette_probabilities",
]
