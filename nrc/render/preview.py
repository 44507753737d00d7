"""``renderer=preview``: a quick, deterministic look at the medium, NOT a light-transport render.

Each pixel shows the environment (or black) seen through the medium, ``L_env * T``, plus a grey
``1 - T`` where the medium blocks the view; ``T`` is the camera ray's transmittance by midpoint
quadrature with half-voxel steps. No scattering is simulated: use it to frame the camera and check
the volume's placement, not as an image of the scene.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from nrc.config import ConfigReader
from nrc.render.result import RenderResult
from nrc.scene import Scene
from nrc.transport.lights import EnvironmentLight


def camera_transmittance(scene: Scene, origin: torch.Tensor, direction: torch.Tensor, step: float) -> torch.Tensor:
    """Transmittance ``(N,)`` of rays through the medium by midpoint quadrature with spacing ``<= step``."""
    grid = scene.grid
    t0, t1 = grid.box.intersect(origin, direction)
    n_steps = max(1, int(np.ceil(float((t1 - t0).max()) / step)))
    tau = torch.zeros_like(t0)
    h = (t1 - t0) / n_steps
    for k in range(n_steps):  # loop over steps along the rays, all rays at once
        x = origin + (t0 + (k + 0.5) * h)[:, None] * direction
        tau = tau + grid.sigma_t(x) * h
    return torch.exp(-tau)


def medium_alpha(scene: Scene, chunk: int = 1 << 16) -> np.ndarray:
    """``(H, W)`` float32 ``1 - T`` of the camera rays through the pixel centres (no scattering): where the image
    sees the medium (``nrc.metrics.medium_mask`` of it; a reference's ``A`` channel, a render's ``alpha.exr``).

    ``T`` by midpoint quadrature with one-voxel steps (:func:`camera_transmittance`): cheap (a few seconds at
    480 x 270 on a quiet machine) and plenty for a mask of "pixels where the medium is seen".
    """
    cam, dev = scene.camera, scene.device
    alpha = torch.zeros(cam.num_pixels, dtype=torch.float32, device=dev)
    with torch.no_grad():
        for s in range(0, cam.num_pixels, chunk):
            pix = torch.arange(s, min(s + chunk, cam.num_pixels), device=dev)
            o, d = cam.generate_rays(pix, torch.full((len(pix), 2), 0.5, device=dev))
            alpha[pix] = 1.0 - camera_transmittance(scene, o, d, scene.grid.voxel_size)
    return alpha.reshape(cam.height, cam.width).cpu().numpy().clip(0.0, 1.0)


@dataclass(frozen=True)
class PreviewSettings:
    """The validated ``renderer`` block of ``renderer=preview`` (defaults in ``conf/renderer/preview.yaml``)."""

    chunk: int
    """Camera rays per batch (memory grows linearly with it)."""

    @classmethod
    def from_config(cls, renderer: Any) -> PreviewSettings:
        cfg = ConfigReader(renderer, "renderer")
        cfg.get_choice("name", ["preview"])
        settings = cls(chunk=cfg.get_int("chunk", lo=1))
        cfg.finish()
        return settings

    @classmethod
    def from_app_config(cls, cfg: Any) -> PreviewSettings:
        """From the app config: its ``renderer`` block."""
        return cls.from_config(cfg.renderer)


class PreviewRenderer:
    """Transmittance-only preview (see module docstring)."""

    name = "preview"

    def __init__(self, scene: Scene, settings: PreviewSettings) -> None:
        self.scene = scene
        self.settings = settings
        self.chunk = self.settings.chunk

    def render(self, progress: bool = False) -> RenderResult:
        scene, cam = self.scene, self.scene.camera
        start = time.perf_counter()
        envs = scene.lights_of(EnvironmentLight)
        background = torch.zeros(3, device=scene.device)
        for env in envs:
            mean = env.radiance if env.radiance is not None else env.image.reshape(-1, 3).mean(0)
            background = background + env.scale * mean
        out = torch.empty(cam.num_pixels, 3, device=scene.device)
        jitter = torch.full((1, 2), 0.5, device=scene.device)
        for s in range(0, cam.num_pixels, self.chunk):
            pix = torch.arange(s, min(s + self.chunk, cam.num_pixels), device=scene.device)
            o, d = cam.generate_rays(pix, jitter.expand(len(pix), 2))
            T = camera_transmittance(scene, o, d, 0.5 * scene.grid.voxel_size)
            out[pix] = background * T[:, None] + 0.5 * (1.0 - T)[:, None]
        image = out.reshape(cam.height, cam.width, 3).cpu().numpy()
        metrics: dict[str, Any] = {"renderer": self.name, "note": "transmittance-only preview, no scattering",
                                   "time_total_s": time.perf_counter() - start}
        return RenderResult(image=image, metrics=metrics)
