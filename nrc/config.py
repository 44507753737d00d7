"""Configuration, the ground floor every other module may use: typed reading of config blocks, composing the
app config, file paths and the device.

* :class:`ConfigReader` reads one block (plain mappings or Hydra ``DictConfig``), checks each value's type
  and range, and raises :class:`~nrc.errors.ConfigError` with the full dotted key (e.g.
  ``encoding.position.n_levels must be >= 1, got 0``). After reading, :meth:`ConfigReader.finish` rejects keys
  the block does not know, so typos never pass silently. Every component's settings dataclass is built by it.
* :func:`compose` -- the resolved app config for a list of overrides, as ``python -m nrc`` sees it (every
  script composes through it); :func:`absolute_paths` resolves the config's file paths against the launch
  directory; :func:`resolve_device` checks ``device``.
* :func:`preset` -- the overrides of a scene type (:data:`PRESETS`, the files of ``conf/scene/``);
  :func:`config_hash` / :func:`scene_hash` -- what a reference (and a render's metrics) is keyed by.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from nrc.errors import ConfigError

def _conf_dir() -> str:
    """The Hydra configs: ``nrc/conf/`` inside an installed wheel (setup.py copies them there), else the
    checkout's ``conf/`` (editable installs and running from the repo)."""
    packaged = Path(__file__).resolve().parent / "conf"
    return str(packaged if (packaged / "config.yaml").is_file() else Path(__file__).resolve().parent.parent / "conf")


CONF_DIR = _conf_dir()

_REQUIRED = object()

# The scene types (``preset("side_lit")`` is ``scene=side_lit``): the files of conf/scene/ (the Disney cloud's ones
# read ../shared/data relative to the working directory); ``none`` adds nothing.
PRESETS: tuple[str, ...] = (*sorted(p.stem for p in (Path(CONF_DIR) / "scene").glob("*.yaml") if p.stem != "base"),
                            "none")
PRESET_SIZES = {"lantern": ["scene.camera.width=80", "scene.camera.height=45"]}  # the size its runs were measured at


def preset(name: str) -> list[str]:
    """The overrides of the scene type ``name`` (one of :data:`PRESETS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown scene type {name!r}: one of {', '.join(PRESETS)}")
    return [] if name == "none" else [f"scene={name}", *PRESET_SIZES.get(name, [])]


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

    def get_int_or_auto(self, name: str, default: Any = _REQUIRED, lo: int | None = None,
                        hi: int | None = None) -> int | None:
        """``auto`` (``None``: the caller's rule decides) or an integer as :meth:`get_int` reads it; ``default``
        may be ``"auto"``."""
        return self._or_auto(name, default, "an integer", lambda d: self.get_int(name, d, lo, hi))

    def get_float_or_auto(self, name: str, default: Any = _REQUIRED, lo: float | None = None,
                          hi: float | None = None, lo_open: bool = False, hi_open: bool = False) -> float | None:
        """``auto`` (``None``: the caller's rule decides) or a number as :meth:`get_float` reads it; ``default``
        may be ``"auto"``."""
        return self._or_auto(name, default, "a number", lambda d: self.get_float(name, d, lo, hi, lo_open, hi_open))

    def _or_auto(self, name: str, default: Any, kind: str, read: Any) -> Any:
        value = self._get(name)
        if value == "auto" or (value is None and default == "auto"):
            return None
        if isinstance(value, str):
            raise ConfigError(f"{self.key(name)} must be auto or {kind}, got {value!r}")
        return read(default)

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


def compose(overrides: Sequence[str] | None = None, return_hydra_config: bool = False) -> Any:
    """The app config (``conf/config.yaml``) with ``overrides`` applied, as ``python -m nrc`` would see it.

    Hydra composes the config groups an override list picks (``scene=sun_sky``, ``renderer=nrc``,
    ``+experiment=...``), then applies the value overrides (``scene.integrator.seed=3``, ``+key=v``, ``~key``) to
    the result. The first part is cached per list of group overrides (composing reads and merges a dozen YAML
    files, ~0.1 s); the second is Hydra's own code on a copy, ~5 ms: the same config, 20x faster for the scripts and
    tests that compose hundreds of configs. Anything else (``hydra/...`` groups, package overrides, the Hydra node
    asked for, or any error) goes through Hydra's ``compose`` whole, so its errors are Hydra's.
    """
    overrides = list(overrides or [])
    if not return_hydra_config:
        fast = _compose_cached(overrides)
        if fast is not None:
            return fast
    return _hydra_compose(overrides, return_hydra_config)


def _hydra_compose(overrides: list[str], return_hydra_config: bool = False) -> Any:
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside a Hydra app (a sweep's callbacks): its search path is ours
        return hydra_compose(config_name="config", overrides=overrides, return_hydra_config=return_hydra_config)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return hydra_compose(config_name="config", overrides=overrides, return_hydra_config=return_hydra_config)


_GROUPS_COMPOSED: dict[tuple[str, ...], Any] = {}  # group overrides -> their composed config (never handed out)
_GROUPS_KEPT = 64


def _compose_cached(overrides: list[str]) -> Any:
    """:func:`compose` through the cache of group compositions, or None where that path does not apply."""
    import copy

    try:
        from hydra._internal.config_loader_impl import ConfigLoaderImpl
        from hydra.core.override_parser.overrides_parser import OverridesParser

        parsed = OverridesParser.create().parse_overrides(overrides)
        groups, values = [], []
        for o in parsed:
            if o.key_or_group.startswith("hydra") or o.package is not None:
                return None
            is_group = (Path(CONF_DIR) / o.key_or_group).is_dir()
            (groups if is_group else values).append(o)
        key = tuple(o.input_line for o in groups)
        base = _GROUPS_COMPOSED.get(key)
        if base is None:
            base = _hydra_compose(list(key))
            _GROUPS_COMPOSED[key] = base
            while len(_GROUPS_COMPOSED) > _GROUPS_KEPT:
                del _GROUPS_COMPOSED[next(iter(_GROUPS_COMPOSED))]
        cfg = copy.deepcopy(base)
        ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
        return cfg
    except Exception:  # noqa: BLE001 -- Hydra's compose says what is wrong, in its own words
        return None


def absolute_paths(cfg: Any) -> None:
    """Resolve the config's relative file paths (scene volume and light files, ``renderer.reference`` /
    ``resume``) against the directory the job was launched from (Hydra's original working directory when
    inside a Hydra job, else the current directory)."""
    try:
        from hydra.utils import to_absolute_path
        absolute = to_absolute_path
    except ImportError:  # pragma: no cover - hydra-core is a dependency
        absolute = lambda p: str(Path(p).resolve())  # noqa: E731

    # Values of the wrong type are left alone here: the typed loaders report them, naming the key.
    scene = cfg.get("scene")
    vol = scene.get("volume") if OmegaConf.is_dict(scene) else None
    if OmegaConf.is_dict(vol) and isinstance(vol.get("path"), str) and vol.get("path"):
        vol.path = absolute(vol.path)
    lights = scene.get("lights") if OmegaConf.is_dict(scene) else None
    for light in lights if OmegaConf.is_list(lights) else []:
        if OmegaConf.is_dict(light) and isinstance(light.get("path"), str) and light.get("path"):
            light.path = absolute(light.path)
    renderer = cfg.get("renderer")
    for key in ("reference", "resume"):
        if OmegaConf.is_dict(renderer) and isinstance(renderer.get(key), str) and renderer.get(key):
            renderer[key] = absolute(renderer[key])


HASHED_SECTIONS = ("scene", "renderer", "transmittance")
CHUNKED_KEYS = ("spp", "seed")  # scene.integrator keys that chunking a reference changes: not hashed


def config_hash(cfg: Any) -> str:
    """sha256 (hex) of the resolved ``scene``, ``renderer`` and ``transmittance`` sections.

    ``scene.integrator.spp`` and ``scene.integrator.seed`` are excluded (chunking changes them); keys are
    sorted, so the hash depends on values only, not on the order of overrides.
    """
    sections = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in HASHED_SECTIONS if k in cfg}
    sections = copy.deepcopy(sections)
    for key in CHUNKED_KEYS:
        sections["scene"].get("integrator", {}).pop(key, None)
    text = json.dumps(sections, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def scene_hash(cfg: Any) -> str:
    """sha256 (hex) of the resolved ``scene`` section alone, without ``integrator.spp`` and ``integrator.seed``.

    Every unbiased estimator (any ``pt`` backend, any unbiased transmittance estimator) converges to the
    same image, so a reference is valid for every config with the same scene hash.
    """
    scene = copy.deepcopy(OmegaConf.to_container(cfg.scene, resolve=True))
    for key in CHUNKED_KEYS:
        scene.get("integrator", {}).pop(key, None)
    # file paths: one spelling per file ("/a/b/../c" and "/a/c" are the same volume)
    for item in [scene.get("volume") or {}, *(scene.get("lights") or [])]:
        if item.get("path"):
            item["path"] = os.path.realpath(item["path"])
    return hashlib.sha256(json.dumps(scene, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def resolve_device(name: str) -> Any:
    """``cpu``, ``cuda`` or ``cuda:N`` as a ``torch.device``; a clear error when CUDA is asked for and absent."""
    import torch

    if not isinstance(name, str) or not (name == "cpu" or name.startswith("cuda")):
        raise ConfigError(f"device must be 'cpu' or 'cuda[:N]', got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={name} was requested but CUDA is not available on this machine; use device=cpu")
    try:
        return torch.device(name)
    except RuntimeError:
        raise ConfigError(f"device must be 'cpu' or 'cuda[:N]', got {name!r}") from None


def code_version() -> str:
    """``nrc <version> (<git rev>[+dirty])`` of the code running (the git revision only when the package's own
    files are tracked by git: an editable install of a checkout, never a wheel)."""
    import subprocess
    from importlib.metadata import PackageNotFoundError, version

    try:
        pkg = version("nrc")
    except PackageNotFoundError:  # pragma: no cover - running from a plain checkout
        pkg = "unknown"
    here = str(Path(__file__).resolve().parent)

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", here, *args], capture_output=True, text=True, check=True,
                              timeout=10).stdout.strip()

    try:
        git("ls-files", "--error-unmatch", "config.py")  # this file is in a git work tree: a checkout
        rev = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return f"nrc {pkg}"
    return f"nrc {pkg} ({rev}{'+dirty' if dirty else ''})"


THREADS_ENV = "NRC_THREADS"  # the threads a sweep's launcher grants each job (set by nrc.app.SweepSetup)


def job_threads(value: Any = "auto") -> int:
    """The CPU threads a job renders with (the ``threads`` setting): an integer as given, else ``auto``: what the
    launcher grants each job (``$NRC_THREADS``, set for a parallel sweep's workers: the cores / the jobs running at
    once), else what Slurm grants the task (``$SLURM_CPUS_PER_TASK``), else torch's own count (the cores this
    process may use, or ``OMP_NUM_THREADS``)."""
    import os

    if value is None or value == "auto":
        for name in (THREADS_ENV, "SLURM_CPUS_PER_TASK"):
            given = os.environ.get(name, "")
            if given.isdigit() and int(given) >= 1:
                return int(given)
        import torch  # only here: a sweep's launching process may not need it

        return torch.get_num_threads()
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"threads must be a positive integer or auto, got {value!r}")
    return value


def apply_threads(value: Any = "auto") -> int:
    """Set torch's intra-op threads to :func:`job_threads` (``value``) and return the count."""
    import torch

    n = job_threads(value)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n
