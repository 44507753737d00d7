"""The scene contract (``../shared/SCENE.md``): validate a ``scene`` config and build a :class:`Scene`.

Every key of the contract is checked on load; a bad value stops with one :class:`~nrc.errors.ConfigError`
whose message names the key (``scene.volume.g must be in (-1, 1), got 1.2``). Keys beyond the contract are
allowed where SCENE.md allows them (``scene.volume.procedural`` holds the built-in cloud's settings).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from nrc.errors import ConfigError, NRCError
from nrc.camera import Camera
from nrc.transport.lights import DirectionalLight, EnvironmentLight, Light, PointLight
from nrc.volume import DensityGrid, procedural_cloud, read_npz, read_vdb
from nrc.volume.procedural import KINDS as PROCEDURAL_KINDS

VOLUME_SOURCES = ("procedural", "vdb", "npz")
ANIMATIONS = ("none", "orbit", "sun")  # renderer.animate.mode
LIGHT_TYPES = ("directional", "point", "environment")


@dataclass(frozen=True)
class Integrator:
    max_scatter: int  # maximum number of real scattering events on a path
    spp: int  # samples per pixel of one frame
    seed: int  # random seed


@dataclass(frozen=True)
class Scene:
    """A validated scene: the medium, its phase and albedo, camera, lights and integrator settings."""

    grid: DensityGrid
    albedo: float
    g: float
    camera: Camera
    lights: tuple[Light, ...]
    integrator: Integrator

    @property
    def device(self) -> torch.device:
        return self.grid.device

    def lights_of(self, kind: type) -> list[Any]:
        return [light for light in self.lights if isinstance(light, kind)]

    def device_for(self, cfg: Mapping[str, Any]) -> torch.device:
        """The device a renderer runs on: the scene's, which must be the one the root config's ``device`` names
        (a scene built by ``load_scene(cfg.scene)`` without a device is on the CPU; a renderer given it under
        ``device=cuda`` would otherwise run silently on the CPU)."""
        wanted = cfg.get("device") if hasattr(cfg, "get") else None
        if wanted is not None and torch.device(str(wanted)).type != self.device.type:
            raise ConfigError(f"device={wanted} but the scene was built on {self.device.type}: build it with "
                              "load_scene(cfg.scene, cfg.device)")
        return self.device


# ---------------------------------------------------------------------------- animation
def rotation_y(degrees: float, device: torch.device) -> torch.Tensor:
    """``(3, 3)`` rotation about world +y (right-handed) by ``degrees``."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float32, device=device)


def animated_scene(scene: Scene, mode: str, degrees_per_frame: float, frame: int) -> Scene:
    """The scene of ``frame`` of an animation (``renderer.animate``; every renderer and benchmark uses this rule):
    ``orbit`` turns the camera by ``degrees_per_frame * frame`` about world +y through the medium box's centre;
    ``sun`` turns every directional light's direction by that angle about world +y (point and environment lights
    stay); ``none`` and frame 0 return ``scene`` itself."""
    if mode not in ANIMATIONS:
        raise ConfigError(f"renderer.animate.mode must be one of {', '.join(ANIMATIONS)}, got {mode!r}")
    if mode == "none" or frame == 0:
        return scene
    degrees = float(degrees_per_frame) * frame
    if mode == "sun":
        return replace(scene, lights=turned_suns(scene.lights, degrees))
    rot, cam, centre = rotation_y(degrees, scene.device), scene.camera, scene.grid.box.center
    return replace(scene, camera=replace(cam, position=rot @ (cam.position - centre) + centre,
                                         forward=rot @ cam.forward, right=rot @ cam.right, up=rot @ cam.up))


def turned_suns(lights: Sequence[Light], degrees: float) -> tuple[Light, ...]:
    """``lights`` with every directional light's direction turned by ``degrees`` about world +y (the others
    as they are): ``animate.mode=sun``."""
    out = []
    for lt in lights:
        if isinstance(lt, DirectionalLight):
            lt = replace(lt, direction=rotation_y(degrees, lt.direction.device) @ lt.direction)
        out.append(lt)
    return tuple(out)


# ---------------------------------------------------------------------------- value checks
def _get(node: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in node:
        raise ConfigError(f"{where}.{key} is missing")
    return node[key]


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{key} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"{key} must be finite, got {value!r}")
    return float(value)


def _integer(value: Any, key: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{key} must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{key} must be >= {minimum}, got {value}")
    return int(value)


def _vec3(value: Any, key: str, nonnegative: bool = False) -> list[float]:
    if not isinstance(value, (Sequence, ListConfig)) or isinstance(value, str) or len(value) != 3:
        raise ConfigError(f"{key} must be a list of 3 numbers, got {value!r}")
    out = [_number(v, key) for v in value]
    if nonnegative and min(out) < 0:
        raise ConfigError(f"{key} must be non-negative, got {out}")
    return out


def _tensor(values: Any, device: torch.device) -> torch.Tensor:
    """A float32 tensor on ``device`` from a list of numbers or an array."""
    return torch.tensor(values, dtype=torch.float32, device=device)


def _existing_file(value: Any, key: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{key} must be a file path, got {value!r}")
    path = Path(value).expanduser()
    if not path.is_file():
        raise ConfigError(f"{key}: file not found: {path}")
    return path


# ---------------------------------------------------------------------------- sections
def load_density(volume: Mapping[str, Any]) -> np.ndarray | torch.Tensor:
    """The raw density grid ``D`` named by a ``scene.volume`` config (no placement, no scaling)."""
    source = _get(volume, "source", "scene.volume")
    if source == "procedural":
        proc = volume.get("procedural") or {}
        res = proc.get("resolution", 128)
        res_list = [res] * 3 if isinstance(res, int) else list(res)
        if len(res_list) != 3 or any(isinstance(r, bool) or not isinstance(r, int) or r < 8 for r in res_list):
            raise ConfigError(f"scene.volume.procedural.resolution must be an int >= 8 or 3 of them, got {res!r}")
        seed = _integer(proc.get("seed", 0), "scene.volume.procedural.seed", 0)
        kind = proc.get("kind", "blobs")
        if kind not in PROCEDURAL_KINDS:
            raise ConfigError(f"scene.volume.procedural.kind must be one of {', '.join(PROCEDURAL_KINDS)}, "
                              f"got {kind!r}")
        return procedural_cloud(res if isinstance(res, int) else res_list, seed, kind)
    if source == "vdb":
        path = _existing_file(volume.get("path"), "scene.volume.path")
        return read_vdb(path, volume.get("grid"))
    if source == "npz":
        path = _existing_file(volume.get("path"), "scene.volume.path")
        return read_npz(path, volume.get("grid"))
    raise ConfigError(f"scene.volume.source must be one of {', '.join(VOLUME_SOURCES)}, got {source!r}")


def _camera(cam: Mapping[str, Any], device: torch.device) -> Camera:
    w = "scene.camera"
    position = _vec3(_get(cam, "position", w), f"{w}.position")
    look_at = _vec3(_get(cam, "look_at", w), f"{w}.look_at")
    up = _vec3(_get(cam, "up", w), f"{w}.up")
    fov = _number(_get(cam, "fov_y", w), f"{w}.fov_y")
    if not 0 < fov < 180:
        raise ConfigError(f"{w}.fov_y must be in (0, 180) degrees, got {fov}")
    width = _integer(_get(cam, "width", w), f"{w}.width", 1)
    height = _integer(_get(cam, "height", w), f"{w}.height", 1)
    fwd = np.subtract(look_at, position)
    if np.linalg.norm(fwd) == 0:
        raise ConfigError(f"{w}.look_at must differ from {w}.position")
    if np.linalg.norm(np.cross(fwd, up)) <= 1e-6 * np.linalg.norm(fwd) * max(np.linalg.norm(up), 1e-30):
        raise ConfigError(f"{w}.up must not be parallel to the view direction (look_at - position)")
    pos, target, up_t = (_tensor(v, device) for v in (position, look_at, up))
    return Camera.look_at(pos, target, up_t, fov, width, height)


def _light(spec: Mapping[str, Any], index: int, device: torch.device) -> Light:
    w = f"scene.lights[{index}]"
    if not isinstance(spec, (Mapping, DictConfig)):
        raise ConfigError(f"{w} must be a mapping with a 'type' key, got {spec!r}")
    kind = spec.get("type")
    if kind == "directional":
        d = _vec3(_get(spec, "direction", w), f"{w}.direction")
        n = math.sqrt(sum(c * c for c in d))
        if n == 0:
            raise ConfigError(f"{w}.direction must be non-zero")
        irr = _vec3(_get(spec, "irradiance", w), f"{w}.irradiance", nonnegative=True)
        return DirectionalLight(_tensor([c / n for c in d], device), _tensor(irr, device))
    if kind == "point":
        pos = _vec3(_get(spec, "position", w), f"{w}.position")
        inten = _vec3(_get(spec, "intensity", w), f"{w}.intensity", nonnegative=True)
        return PointLight(_tensor(pos, device), _tensor(inten, device))
    if kind == "environment":
        scale = _number(spec.get("scale", 1.0), f"{w}.scale")
        if scale < 0:
            raise ConfigError(f"{w}.scale must be >= 0, got {scale}")
        has_rad = spec.get("radiance") is not None
        has_path = spec.get("path") is not None
        if has_rad == has_path:
            override = w.replace("[", ".").replace("]", "")
            raise ConfigError(f"{w}: an environment light needs exactly one of 'radiance' (a uniform sky) or 'path' "
                              f"(a lat-long EXR)" + (f"; to use the file, also set {override}.radiance=null"
                                                     if has_rad else ""))
        if has_rad:
            radiance = _vec3(spec["radiance"], f"{w}.radiance", nonnegative=True)
            return EnvironmentLight(_tensor(radiance, device), None, scale)
        from nrc.io.exr import read_exr

        try:
            img, _ = read_exr(_existing_file(spec["path"], f"{w}.path"))
        except ConfigError:
            raise
        except NRCError as exc:
            raise ConfigError(f"{w}.path: {exc}") from None
        if not np.isfinite(img).all() or (img < 0).any():
            raise ConfigError(f"{w}.path: environment image must be finite and non-negative")
        return EnvironmentLight(None, _tensor(img, device), scale)
    raise ConfigError(f"{w}.type must be one of {', '.join(LIGHT_TYPES)}, got {kind!r}")


def load_scene(scene_cfg: DictConfig | Mapping[str, Any], device: torch.device | str = "cpu") -> Scene:
    """Validate a ``scene`` config section and build the :class:`Scene` on ``device``."""
    cfg = OmegaConf.to_container(scene_cfg, resolve=True) if isinstance(scene_cfg, DictConfig) else scene_cfg
    device = torch.device(device)
    volume = _get(cfg, "volume", "scene")
    w = "scene.volume"
    scale = _number(_get(volume, "density_scale", w), f"{w}.density_scale")
    if scale < 0:
        raise ConfigError(f"{w}.density_scale must be >= 0, got {scale}")
    albedo = _number(_get(volume, "albedo", w), f"{w}.albedo")
    if not 0 <= albedo <= 1:
        raise ConfigError(f"{w}.albedo must be in [0, 1], got {albedo}")
    g = _number(_get(volume, "g", w), f"{w}.g")
    if not -1 < g < 1:
        raise ConfigError(f"{w}.g must be in (-1, 1), got {g}")
    center = _vec3(_get(volume, "center", w), f"{w}.center")
    diagonal = _number(_get(volume, "diagonal", w), f"{w}.diagonal")
    if diagonal <= 0:
        raise ConfigError(f"{w}.diagonal must be > 0, got {diagonal}")
    camera = _camera(_get(cfg, "camera", "scene"), device)
    lights_cfg = cfg.get("lights") or []
    if not isinstance(lights_cfg, (list, tuple, ListConfig)):
        raise ConfigError(f"scene.lights must be a list, got {lights_cfg!r}")
    lights = tuple(_light(spec, i, device) for i, spec in enumerate(lights_cfg))
    integ = _get(cfg, "integrator", "scene")
    wi = "scene.integrator"
    integrator = Integrator(
        max_scatter=_integer(_get(integ, "max_scatter", wi), f"{wi}.max_scatter", 0),
        spp=_integer(_get(integ, "spp", wi), f"{wi}.spp", 1),
        seed=_integer(_get(integ, "seed", wi), f"{wi}.seed", 0),
    )
    grid = DensityGrid(torch.as_tensor(load_density(volume)), center, diagonal, scale, device)
    return Scene(grid, albedo, g, camera, lights, integrator)
