"""Training paths of a frame: where they start on screen, and the records they leave behind.

* Training pixels form a ``width x height`` training image tiled over the screen: training pixel
  ``(tx, ty)`` starts its path at image-plane position ``((tx + ox) W / width, (ty + oy) H / height)``
  in pixel units, with one random offset ``(ox, oy)`` in ``[0, 1)^2`` per frame (x and y spacing each
  from their own axis, so every training path lies inside the image).
* Paths are traced in the batch filter's buffer order: path ``k`` belongs to training pixel
  ``order[k]`` and owns records ``[k V, (k + 1) V)``, so a filter batch of pixels ``[a, b)`` is the
  record slice ``[a V, b V)``.
* Targets follow ``T_j = acc_j + albedo x T_{j+1}`` (see :mod:`nrc.render.radiance_caching.paths`).
* The training budget (``renderer.training.width/height: auto``) is sized to the pixels that see the medium
  (:func:`medium_pixels`, :func:`auto_training_size`): training paths = ``paths_per_pixel`` x those pixels,
  clamped to ``[min_paths, max_paths]``, on a training image of the screen's aspect whose sides are multiples
  of :data:`SIDE_MULTIPLE` (every batch filter divides them); records per frame are ``records_per_path``
  times the paths.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nrc.render.radiance_caching.ring_buffer import TrainingRecords
from nrc.volume.optical_depth import centre_ray_chords


def training_positions(order: Tensor, train_width: int, train_height: int, image_width: int, image_height: int,
                       offset: Tensor) -> Tensor:
    """``(N, 2)`` image-plane positions (pixel units) of the training pixels listed by ``order``.

    Args:
        order: ``(N,)`` flat training-pixel indices ``ty * train_width + tx`` in buffer order.
        offset: ``(2,)`` the frame's random offset ``(ox, oy)`` in ``[0, 1)``.
    """
    tx = (order % train_width).to(torch.float32)
    ty = torch.div(order, train_width, rounding_mode="floor").to(torch.float32)
    x = (tx + offset[0]) * (image_width / train_width)
    y = (ty + offset[1]) * (image_height / train_height)
    return torch.stack([x, y], dim=1)


def training_targets(acc: Tensor, n_paths: int, records_per_path: int, albedo: float) -> Tensor:
    """Targets ``(n_paths * V, 3)`` from the per-record accumulators ``acc`` ``(n_paths * V, 3)``.

    Runs ``T_j = acc_j + albedo x T_{j+1}`` backwards over the ``V`` records of every path (a record
    whose vertex does not exist has ``acc = 0``, so it adds nothing).
    """
    t = acc.reshape(n_paths, records_per_path, 3).clone()
    for j in range(records_per_path - 2, -1, -1):
        t[:, j] += albedo * t[:, j + 1]
    return t.reshape(-1, 3)


def frame_records(rec_x: Tensor, rec_d: Tensor, targets: Tensor, rec_valid: Tensor) -> tuple[TrainingRecords, Tensor]:
    """The frame's records and their validity (existing, non-terminal vertices with finite targets)."""
    valid = rec_valid & torch.isfinite(targets).all(dim=1)
    targets = torch.where(valid[:, None], targets, torch.zeros_like(targets))
    return TrainingRecords(rec_x, rec_d, targets), valid


SIDE_MULTIPLE = 16  # auto training image sides are multiples of this (batch filters split them evenly)
MEDIUM_SAMPLES = 48  # density lookups along a pixel's centre ray when counting the pixels that see the medium


def medium_pixels(camera, grid, samples: int = MEDIUM_SAMPLES, chunk: int = 1 << 15) -> int:
    """How many pixels :func:`medium_pixel_mask` selects."""
    return int(medium_pixel_mask(camera, grid, samples, chunk).sum())


def medium_pixel_mask(camera, grid, samples: int = MEDIUM_SAMPLES, chunk: int = 1 << 15) -> Tensor:
    """``(H, W)`` bool: pixels whose centre ray meets nonzero density: ``samples`` stratified midpoints of the
    ray's segment inside the grid's box are looked up (a medium thinner than the spacing can be missed; the mask
    sizes a budget and selects pixels for the flicker figure, it is not an estimator). Memory: ``chunk x samples``
    lookups at a time."""
    dev = grid.device
    out = torch.zeros(camera.num_pixels, dtype=torch.bool, device=dev)
    mid = (torch.arange(samples, device=dev, dtype=torch.float32) + 0.5) / samples
    for pix, o, d, t0, t1 in centre_ray_chords(camera, grid, chunk):
        t = t0[:, None] + (t1 - t0)[:, None] * mid[None]
        x = o[:, None, :] + t[..., None] * d[:, None, :]
        dens = grid.lookup(x.reshape(-1, 3)).reshape(len(o), samples)
        out[pix] = (dens > 0).any(dim=1)
    return out.reshape(camera.height, camera.width)


def auto_training_size(n_medium: int, image_width: int, image_height: int, paths_per_pixel: float,
                       min_paths: int, max_paths: int) -> tuple[int, int]:
    """``(width, height)`` of the auto training image: about ``clamp(paths_per_pixel x n_medium, min_paths,
    max_paths)`` paths, the image's aspect, sides multiples of :data:`SIDE_MULTIPLE` (at least one multiple)."""
    paths = min(max(paths_per_pixel * n_medium, min_paths), max_paths)
    aspect = image_width / image_height
    m = SIDE_MULTIPLE
    width = max(1, round(math.sqrt(paths * aspect) / m)) * m
    height = max(1, round(paths / width / m)) * m
    return width, height
