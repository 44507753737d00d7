"""Per-frame logging of the NRC renderer: TensorBoard scalars and images, and the run's history.

TensorBoard tags: ``loss/step`` (every training step), ``loss/frame`` (mean per frame), ``time/<stage>``
for ``trace`` (with its parts ``free_flight`` and ``shadow``), ``infer``, ``train`` (what the frame waited for),
``train_work`` (the steps on the frame's records, wherever they ran) and ``frame`` (seconds), ``error/rel_mse``
and ``error/mse`` when a reference is given, ``error/flicker`` (the mean frame-to-frame change over the pixels
that see the medium, relative to their mean), ``train/lr_mlp`` (the MLP's learning rate for the next step),
``debias/<counter>`` with ``renderer.debias`` (``debias.py``),
``reuse/<counter>`` with ``renderer.reuse``, ``light/<counter>`` (the light sampling), ``image/frame`` /
``image/output`` (tone-mapped) every ``image_every`` frames, each with one exposure for the whole run (with
``exposure: auto``, the exposure of its first logged image) so the images show the convergence.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from nrc.errors import ConfigError
from nrc.io.png import DisplaySettings, tonemap


# per-frame light-sampling counters and settings logged under TensorBoard's light/ (nrc.transport.light_sampling)
LIGHT_SCALARS = ("shadow_rays", "equiangular_segments", "ris_candidates", "light_selection_entropy_bits",
                 "nee_lights")


class FrameLog:
    """Collects per-frame statistics (``history``) and mirrors them to TensorBoard when ``log_dir`` is set."""

    def __init__(self, log_dir: Path | None, image_every: int, display: DisplaySettings | None = None) -> None:
        self.history: dict[str, list[Any]] = {}
        self.image_every = image_every
        self.display = display or DisplaySettings()
        self.exposure: dict[str, float] = {}  # per image name, fixed at its first log (auto: from that image)
        self.writer = None
        if log_dir is not None:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(log_dir))

    def steps(self, first_step: int, losses: list[float]) -> None:
        if self.writer is not None:
            for i, loss in enumerate(losses):
                self.writer.add_scalar("loss/step", loss, first_step + i)

    def trained(self, frame: int, first_step: int, losses: list[float], seconds: float, beside: bool) -> None:
        """The training steps on frame ``frame``'s records, taken after the frame was logged (``beside``: during the
        next frame's trace; ``renderer.training.overlap``): its ``loss``, ``train_steps``, ``time_train_work_s`` and
        ``train_beside_trace`` (history, ``loss/frame``, ``time/train_work``), and the steps (``loss/step``). The
        history holds every frame from frame 0 on."""
        loss = float(np.mean(losses)) if losses else None
        for key, value in (("loss", loss), ("train_steps", len(losses)), ("time_train_work_s", seconds),
                           ("train_beside_trace", beside)):
            self.history[key][frame] = value
        self.steps(first_step, losses)
        if self.writer is not None:
            self.writer.add_scalar("time/train_work", seconds, frame)
            if loss is not None:
                self.writer.add_scalar("loss/frame", loss, frame)

    def frame(self, frame: int, stats: dict[str, Any], images: dict[str, np.ndarray], force_images: bool = False
              ) -> None:
        """Record the scalars of ``stats`` (per-frame lists in :attr:`history`) and log them; the images every
        ``image_every`` frames and when ``force_images`` (the final frame)."""
        for key, value in stats.items():
            self.history.setdefault(key, []).append(value)
        if self.writer is None:
            return
        for key, value in stats.items():
            if key.startswith("time_") and key.endswith("_s") and value is not None:
                self.writer.add_scalar(f"time/{key[5:-2]}", value, frame)
            elif key in ("loss", "rel_mse", "mse") and value is not None:
                self.writer.add_scalar("loss/frame" if key == "loss" else f"error/{key}", value, frame)
            elif key == "flicker" and value is not None:  # mean |I_t - I_t-1| over the medium (renderer._flicker)
                self.writer.add_scalar("error/flicker", value, frame)
            elif key == "lr_mlp" and value is not None:  # the MLP's learning rate (cache.optimizer.lr_final_fraction)
                self.writer.add_scalar("train/lr_mlp", value, frame)
            elif key in LIGHT_SCALARS and value is not None:
                self.writer.add_scalar(f"light/{key}", value, frame)
            elif key.startswith("reuse_") and value is not None:  # reservoir reuse counters (nrc/render/reuse)
                self.writer.add_scalar(f"reuse/{key[6:]}", value, frame)
            elif key.startswith("debias_") and value is not None:  # the control variate (debias.py)
                self.writer.add_scalar(f"debias/{key[7:]}", value, frame)
        if (self.image_every and frame % self.image_every == 0) or force_images:
            for name, img in images.items():
                if name not in self.exposure:
                    self.exposure[name] = self.display.exposure_for(img)
                k = self.exposure[name]
                self.writer.add_image(f"image/{name}", tonemap(img, k, self.display.tonemap), frame,
                                      dataformats="HWC")

    def load(self, history: dict[str, list[Any]]) -> None:
        self.history = {k: list(v) for k, v in history.items()}

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def load_reference(path: str | None, camera: Any) -> np.ndarray | None:
    """``renderer.reference``: the EXR every frame's ``rel_mse`` and ``mse`` compare against, ``(H, W, 3)`` float32
    at the camera's size (``None`` without one); ``ConfigError`` naming the key."""
    if path is None:
        return None
    from nrc.io import read_exr

    if not Path(path).is_file():
        raise ConfigError(f"renderer.reference: no such file {path}")
    ref, _ = read_exr(path)
    if ref.shape[:2] != (camera.height, camera.width):
        raise ConfigError(f"renderer.reference is {ref.shape[1]}x{ref.shape[0]}, the camera renders "
                          f"{camera.width}x{camera.height}")
    return ref[..., :3].astype(np.float32)
