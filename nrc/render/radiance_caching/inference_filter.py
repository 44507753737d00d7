"""The inference filter: cache queries are evaluated in batches, and batches without a query are skipped.

Every path of a frame owns one query slot, in path order (render samples in pixel order, then training
paths), valid when the path terminated into the cache. Slots are grouped into consecutive batches of
``batch_size``; a batch with no valid slot is skipped (no network evaluation), the others evaluate their
valid slots only. Skipped and evaluated batches are counted for the frame's metrics. Optionally the
training paths' slots are answered by a second query function (the raw weights instead of the EMA).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor


def filtered_query(query: Callable[[Tensor, Tensor], Tensor], x: Tensor, d: Tensor, slot: Tensor, n_slots: int,
                   batch_size: int, query_from: Callable[[Tensor, Tensor], Tensor] | None = None,
                   first_slot: int = 0) -> tuple[Tensor, dict[str, int]]:
    """Evaluate ``query(x, d)`` batch by batch; returns the values ``(Q, 3)`` (in input order) and the counts.

    Args:
        query: the cache's query function (positions, directions) -> radiance ``(N, 3)``.
        x, d: ``(Q, 3)`` query positions and directions; ``slot``: ``(Q,)`` their slot ids in ``[0, n_slots)``.
        n_slots: the number of query slots of the frame; batch_size: slots per batch (``>= 1``).
        query_from, first_slot: if given, slots ``>= first_slot`` (the training paths) are evaluated by
            ``query_from`` instead of ``query`` (the renderer's ``training.query_weights: raw``).
    """
    n_batches = -(-n_slots // batch_size) if n_slots else 0
    values = torch.zeros(x.shape[0], 3, dtype=torch.float32, device=x.device)
    batch = torch.div(slot, batch_size, rounding_mode="floor")
    order = torch.argsort(batch, stable=True)
    ids, sizes = torch.unique_consecutive(batch[order], return_counts=True)
    start = 0
    for size in sizes.tolist():
        sel = order[start:start + size]
        if query_from is None:
            values[sel] = query(x[sel], d[sel]).to(values)
        else:
            for part, fn in ((sel[slot[sel] < first_slot], query), (sel[slot[sel] >= first_slot], query_from)):
                if len(part):
                    values[part] = fn(x[part], d[part]).to(values)
        start += size
    evaluated = len(ids)
    return values, {"inference_batches": n_batches, "inference_batches_evaluated": evaluated,
                    "inference_batches_skipped": n_batches - evaluated, "cache_queries": int(x.shape[0])}
