"""Typed, validated reading of the cache's JSON-like config blocks.

The cache is configured by plain mappings (``dict`` or Hydra ``DictConfig``). :class:`ConfigReader`
reads one block, checks each value's type and range, and raises :class:`~nrc.errors.ConfigError`
with the full dotted key (e.g. ``encoding.position.n_levels must be >= 1, got 0``). After reading,
:meth:`ConfigReader.finish` rejects keys the block does not know, so typos never pass silently.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from nrc.errors import ConfigError

_REQUIRED = object()


def to_plain(cfg: Any) -> Any:
    """Convert an OmegaConf container (resolving interpolations) to plain dicts/lists; pass others through."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - hydra-core is a dependency
        return cfg
    if isinstance(cfg, (DictConfig, ListConfig)):
        return OmegaConf.to_container(cfg, resolve=True)
    return cfg


class ConfigReader:
    """Reads the values of one config block named ``path`` (used as the prefix of error messages)."""

    def __init__(self, cfg: Mapping[str, Any] | None, path: str) -> None:
        cfg = to_plain(cfg)
        if cfg is None:
            cfg = {}
        if not isinstance(cfg, Mapping):
            raise ConfigError(f"{path} must be a mapping, got {type(cfg).__name__}")
        self._cfg = dict(cfg)
        self._path = path
        self._used: set[str] = set()

    def key(self, name: str) -> str:
        """The dotted name of ``name`` inside this block."""
        return f"{self._path}.{name}" if self._path else name

    def _get(self, name: str) -> Any:
        """The value of ``name`` (``None`` when absent or null), marking the key as known."""
        self._used.add(name)
        return self._cfg.get(name)

    def _missing(self, name: str, default: Any) -> Any:
        if default is _REQUIRED:
            raise ConfigError(f"{self.key(name)} is required")
        return default

    def get_int(self, name: str, default: Any = _REQUIRED, lo: int | None = None, hi: int | None = None) -> int:
        value = self._get(name)
        if value is None:
            return self._missing(name, default)
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ConfigError(f"{self.key(name)} must be an integer, got {value!r}")
        self._check_range(name, value, lo, hi)
        return value

    def get_float(self, name: str, default: Any = _REQUIRED, lo: float | None = None, hi: float | None = None,
              lo_open: bool = False, hi_open: bool = False) -> float:
        value = self._get(name)
        if value is None:
            return self._missing(name, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{self.key(name)} must be a finite number, got {value!r}")
        value = float(value)
        if lo is not None and (value <= lo if lo_open else value < lo):
            raise ConfigError(f"{self.key(name)} must be {'>' if lo_open else '>='} {lo}, got {value}")
        if hi is not None and (value >= hi if hi_open else value > hi):
            raise ConfigError(f"{self.key(name)} must be {'<' if hi_open else '<='} {hi}, got {value}")
        return value

    def get_bool(self, name: str, default: Any = _REQUIRED) -> bool:
        value = self._get(name)
        if value is None:
            return self._missing(name, default)
        if not isinstance(value, bool):
            raise ConfigError(f"{self.key(name)} must be true or false, got {value!r}")
        return value

    def get_choice(self, name: str, choices: Sequence[str], default: Any = _REQUIRED) -> str:
        """A string matched case-insensitively against ``choices``; returns the canonical spelling."""
        value = self._get(name)
        if value is None:
            return self._missing(name, default)
        canonical = {c.lower(): c for c in choices}
        if not isinstance(value, str) or value.lower() not in canonical:
            raise ConfigError(f"{self.key(name)} must be one of {sorted(canonical.values())}, got {value!r}")
        return canonical[value.lower()]

    def get_raw(self, name: str, default: Any = None) -> Any:
        """The value of ``name`` as it is (``default`` when absent or null), for values the caller checks."""
        value = self._get(name)
        return default if value is None else value

    def get_optional_str(self, name: str) -> str | None:
        """A string (e.g. a file path) or ``None`` when absent or null."""
        value = self._get(name)
        if value is not None and not isinstance(value, str):
            raise ConfigError(f"{self.key(name)} must be a string or null, got {value!r}")
        return value

    def block(self, name: str) -> ConfigReader:
        """The sub-block ``name`` (an empty block when absent)."""
        return ConfigReader(self._get(name), self.key(name))

    def finish(self) -> None:
        """Raise for keys of this block that no reader asked for."""
        unknown = sorted(set(self._cfg) - self._used)
        if unknown:
            raise ConfigError(f"{self._path or 'config'}: unknown key(s) {', '.join(unknown)}")

    def _check_range(self, name: str, value: int, lo: int | None, hi: int | None) -> None:
        if lo is not None and value < lo:
            raise ConfigError(f"{self.key(name)} must be >= {lo}, got {value}")
        if hi is not None and value > hi:
            raise ConfigError(f"{self.key(name)} must be <= {hi}, got {value}")
