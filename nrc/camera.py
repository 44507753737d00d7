"""Pinhole camera (SCENE.md conventions).

The camera sits at ``position`` looking at ``look_at``; ``fov_y`` is the full vertical field of view in
degrees. Image row 0 is the top of the view; image +x (columns) is world ``normalize(cross(forward, up))``.
Each sample's ray passes through a uniformly random point of its pixel (box filter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Camera:
    """A pinhole camera. Vectors are ``(3,)`` float32 tensors on the scene's device."""

    position: Tensor
    forward: Tensor
    right: Tensor
    up: Tensor
    fov_y: float
    width: int
    height: int

    @staticmethod
    def look_at(
        position: Tensor, look_at: Tensor, up: Tensor, fov_y: float, width: int, height: int
    ) -> Camera:
        """Build the orthonormal camera frame; ``up`` need not be orthogonal to the view direction."""
        forward = look_at - position
        forward = forward / forward.norm()
        right = torch.linalg.cross(forward, up)
        right = right / right.norm()
        true_up = torch.linalg.cross(right, forward)
        return Camera(position, forward, right, true_up, float(fov_y), int(width), int(height))

    @property
    def num_pixels(self) -> int:
        return self.width * self.height

    def generate_rays(self, pixel: Tensor, jitter: Tensor) -> tuple[Tensor, Tensor]:
        """Primary rays for pixels.

        Args:
            pixel: ``(N,)`` int64 flat pixel indices ``row * width + col``.
            jitter: ``(N, 2)`` uniform offsets in ``[0, 1)^2`` inside the pixel (x to the right, y down).

        Returns:
            ``(origin, direction)``, each ``(N, 3)``; directions are unit length.
        """
        col = (pixel % self.width).to(jitter.dtype)
        row = torch.div(pixel, self.width, rounding_mode="floor").to(jitter.dtype)
        tan_half = math.tan(math.radians(self.fov_y) * 0.5)
        aspect = self.width / self.height
        sx = ((col + jitter[:, 0]) / self.width * 2.0 - 1.0) * tan_half * aspect
        sy = (1.0 - (row + jitter[:, 1]) / self.height * 2.0) * tan_half
        d = self.forward + sx[:, None] * self.right + sy[:, None] * self.up
        d = d / d.norm(dim=-1, keepdim=True)
        return self.position.expand_as(d), d

    def project(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The pixels that world points ``x`` ``(N, 3)`` are seen through: ``(pixel (N,) int64 flat index,
        inside (N,) bool)`` -- ``inside`` is false for points behind the camera or outside the image (their
        pixel is 0). The inverse of :meth:`generate_rays`: a point on the ray of pixel ``p`` at any jitter
        projects to ``p`` (up to rounding at the pixel's borders)."""
        v = x - self.position
        z = v @ self.forward
        zs = torch.where(z > 0, z, torch.ones_like(z))
        tan_half = math.tan(math.radians(self.fov_y) * 0.5)
        aspect = self.width / self.height
        sx = (v @ self.right) / (zs * tan_half * aspect)
        sy = (v @ self.up) / (zs * tan_half)
        col = torch.floor((sx + 1.0) * 0.5 * self.width)
        row = torch.floor((1.0 - sy) * 0.5 * self.height)
        inside = (z > 0) & (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)
        pixel = torch.where(inside, row.long() * self.width + col.long(), torch.zeros_like(col, dtype=torch.long))
        return pixel, inside
