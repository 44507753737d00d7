"""The environment's directions: the lat-long mapping of SCENE.md (:func:`direction_to_latlong`), uniform directions
on the sphere (the uniform sky's sampling) and the lat-long map's radiance and importance sampling
(:class:`EnvironmentMap`: proportional to luminance x sin(theta) per pixel, bilinear lookup).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nrc.transport.lights import LUMINANCE


def direction_to_latlong(d: Tensor) -> tuple[Tensor, Tensor]:
    """Unit directions ``(N, 3)`` -> lat-long ``(u, v)`` in ``[0, 1)`` x ``[0, 1]`` (SCENE.md mapping)."""
    u = torch.atan2(d[:, 0], -d[:, 2]) / (2.0 * math.pi)
    u = u - torch.floor(u)
    v = torch.acos(d[:, 1].clamp(-1.0, 1.0)) / math.pi
    return u, v


def latlong_to_direction(u: Tensor, v: Tensor) -> Tensor:
    """Inverse of :func:`direction_to_latlong`."""
    phi, theta = 2.0 * math.pi * u, math.pi * v
    s = torch.sin(theta)
    return torch.stack([s * torch.sin(phi), torch.cos(theta), -s * torch.cos(phi)], dim=-1)


def sphere_direction(u0: Tensor, u1: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A uniform direction on the unit sphere (pdf ``1 / 4pi``) from two uniforms, in component form."""
    z = 1.0 - 2.0 * u0
    r = torch.sqrt((1.0 - z * z).clamp(min=0.0))
    phi = 2.0 * math.pi * u1
    return r * torch.cos(phi), r * torch.sin(phi), z


def uniform_sphere(u: Tensor) -> Tensor:
    """Uniform directions on the unit sphere from ``u`` ``(N, 2)`` in ``[0, 1)^2`` (pdf ``1 / 4pi``)."""
    return torch.stack(sphere_direction(u[:, 0], u[:, 1]), dim=-1)


class EnvironmentMap:
    """Lat-long environment radiance with bilinear lookup and importance sampling.

    Args:
        image: ``(H, W, 3)`` radiance, row 0 straight up, column 0 facing -z.
        scale: multiplier of the radiance.
    """

    def __init__(self, image: Tensor, scale: float) -> None:
        self.image = image * scale
        self.h, self.w = image.shape[:2]
        lum = (self.image * torch.tensor(LUMINANCE, device=image.device)).sum(-1)
        theta = (torch.arange(self.h, device=image.device) + 0.5) / self.h * math.pi
        weights = (lum * torch.sin(theta)[:, None]).reshape(-1).double()
        total = float(weights.sum())
        if total <= 0:  # a black map: sample uniformly (its radiance is zero anyway)
            weights = torch.ones_like(weights)
            total = float(weights.numel())
        self.pmf = (weights / total).float()
        self.cdf = torch.cumsum(weights / total, 0).float()
        self.cdf[-1] = 1.0

    def radiance(self, d: Tensor) -> Tensor:
        """Bilinear radiance ``(N, 3)`` for unit directions ``d`` (wraps in u, clamps in v)."""
        u, v = direction_to_latlong(d)
        x = u * self.w - 0.5
        y = (v * self.h - 0.5).clamp(0.0, self.h - 1.0)
        x0 = torch.floor(x)
        y0 = torch.floor(y).clamp(max=max(self.h - 2, 0))
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0i = x0.long() % self.w
        x1i = (x0i + 1) % self.w
        y0i = y0.long()
        y1i = (y0i + 1).clamp(max=self.h - 1)
        img = self.image
        top = img[y0i, x0i] * (1 - fx) + img[y0i, x1i] * fx
        bot = img[y1i, x0i] * (1 - fx) + img[y1i, x1i] * fx
        return top * (1 - fy) + bot * fy

    def sample(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Sample ``(direction (N, 3), solid-angle pdf (N,))`` from ``u`` ``(N, 3)`` in ``[0, 1)^3``."""
        idx = torch.searchsorted(self.cdf, u[:, 0].contiguous(), right=True).clamp(max=self.cdf.numel() - 1)
        row, col = idx // self.w, idx % self.w
        uu = (col.to(u.dtype) + u[:, 1]) / self.w
        vv = (row.to(u.dtype) + u[:, 2]) / self.h
        d = latlong_to_direction(uu, vv)
        return d, self._pdf_of_pixel(idx, vv)

    def pdf(self, d: Tensor) -> Tensor:
        """Solid-angle pdf ``(N,)`` with which :meth:`sample` produces unit directions ``d``."""
        u, v = direction_to_latlong(d)
        col = (u * self.w).long().clamp(0, self.w - 1)
        row = (v * self.h).long().clamp(0, self.h - 1)
        return self._pdf_of_pixel(row * self.w + col, v)

    def _pdf_of_pixel(self, idx: Tensor, v: Tensor) -> Tensor:
        sin_theta = torch.sin(math.pi * v).clamp(min=1e-7)
        return self.pmf[idx] * (self.w * self.h) / (2.0 * math.pi**2 * sin_theta)
