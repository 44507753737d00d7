"""Working-set bookkeeping shared by the wavefront renderers (``pt``, ``nrc``).

A wavefront keeps its paths in a dict of per-path tensors (one row per slot) plus their brick traversal.
When paths finish, their slots are refilled from the queue of paths not yet started; once the queue is
empty, finished slots are dropped (compaction), so every remaining row is a live path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from nrc.errors import ConfigError
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import BrickTraversal, MajorantGrid


def refill_or_compact(s: dict[str, Tensor], trav: BrickTraversal, done: Tensor, next_id: int, total: int,
                      new_paths: Callable[[Tensor], dict[str, Tensor]]) -> tuple[dict[str, Tensor], int]:
    """Refill the finished slots ``done`` with paths ``next_id, next_id + 1, ...`` (while ``< total``), drop the rest.

    Args:
        s: the per-path tensors (every value has one row per slot); ``trav`` their traversal.
        done: ``(K,)`` indices of finished slots.
        next_id: id of the next path to start; ``total``: number of paths in the queue.
        new_paths: builds the per-path tensors of new paths from their ids (same keys as ``s``, with
            ``o``, ``d``, ``t`` and ``t_max`` for the traversal).

    Returns:
        The (possibly compacted) per-path tensors and the next path id.
    """
    k = min(len(done), total - next_id)
    if k:
        fresh = new_paths(torch.arange(next_id, next_id + k, device=done.device))
        slots = done[:k]
        for name, value in fresh.items():
            s[name][slots] = value
        trav.restart(slots, fresh["o"], fresh["d"], fresh["t"], fresh["t_max"])
        next_id += k
        done = done[k:]
    if len(done):
        keep = torch.ones(trav.t.shape[0], dtype=torch.bool, device=done.device)
        keep[done] = False
        s = {name: value[keep] for name, value in s.items()}
        trav.select(keep)
    return s, next_id


def wavefront_majorants(grid: DensityGrid, brick: Any, free_flight: str) -> tuple[MajorantGrid, MajorantGrid]:
    """``(majorants, tracking_majorants)`` of a wavefront renderer from ``renderer.brick`` / ``renderer.free_flight``.

    ``brick`` is ``'auto'`` (:meth:`MajorantGrid.auto_brick`) or an edge in voxels; shadow rays always use
    these brick majorants. Free flights use them too (``free_flight='brick'``) or one majorant for the whole
    box (``'global'``: the same DDA code over a single brick).

    Raises:
        nrc.errors.ConfigError: ``brick`` or ``free_flight`` is invalid (the message names the key).
    """
    if brick == "auto":
        brick = MajorantGrid.auto_brick(grid)
    elif isinstance(brick, bool) or not isinstance(brick, int) or brick < 1:
        raise ConfigError(f"renderer.brick must be 'auto' or an integer >= 1, got {brick!r}")
    if free_flight not in ("brick", "global"):
        raise ConfigError(f"renderer.free_flight must be 'brick' or 'global', got {free_flight!r}")
    majorants = MajorantGrid(grid, brick)
    return majorants, (majorants if free_flight == "brick" else MajorantGrid(grid, 0))
