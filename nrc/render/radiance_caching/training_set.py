"""Training paths of a frame: where they start on screen, and the records they leave behind.

* Training pixels form a ``width x height`` training image tiled over the screen: training pixel
  ``(tx, ty)`` starts its path at image-plane position ``((tx + ox) W / width, (ty + oy) H / height)``
  in pixel units, with one random offset ``(ox, oy)`` in ``[0, 1)^2`` per frame (x and y spacing each
  from their own axis, so every training path lies inside the image).
* Paths are traced in the batch filter's buffer order: path ``k`` belongs to training pixel
  ``order[k]`` and owns records ``[k V, (k + 1) V)``, so a filter batch of pixels ``[a, b)`` is the
  record slice ``[a V, b V)``.
* Targets follow ``T_j = acc_j + albedo x T_{j+1}`` (see :mod:`nrc.render.radiance_caching.paths`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from nrc.render.radiance_caching.ring_buffer import TrainingRecords


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
