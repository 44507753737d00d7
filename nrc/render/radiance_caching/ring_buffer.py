"""A fixed-capacity ring of valid training records from earlier frames, used to fill invalid ones.

A training record is ``(position, direction, target)``, each ``(N, 3)`` float32 on one device. Training
paths that miss the medium or fail give invalid records; instead of training on them (or on a shrinking
batch), the renderer replaces each by a record stored from an earlier frame. Per frame, call
:meth:`RingBuffer.fill` (draws only from earlier frames) and then :meth:`RingBuffer.push`.

The ``valid`` mask is authoritative: records marked valid are stored and passed through as they are.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from nrc.errors import ConfigError


class TrainingRecords(NamedTuple):
    """``positions``, ``directions``, ``targets``: ``(N, 3)`` float32 tensors on one device."""

    positions: Tensor
    directions: Tensor
    targets: Tensor

    def _packed(self) -> Tensor:
        return torch.cat([self.positions, self.directions, self.targets], dim=1)

    @staticmethod
    def _unpack(data: Tensor) -> TrainingRecords:
        return TrainingRecords(*data.split(3, dim=1))


class RingBuffer:
    """``capacity`` training records on ``device``; once full, each push overwrites the oldest records.

    Draws use an explicit ``torch.Generator`` living on the buffer's device.
    """

    def __init__(self, capacity: int, device: torch.device | str = "cpu") -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ConfigError(f"ring_buffer.capacity must be an integer >= 1, got {capacity!r}")
        self.capacity = capacity
        self.device = torch.device(device)
        self._data = torch.zeros(capacity, 9, dtype=torch.float32, device=self.device)
        self._started = torch.full((capacity,), -1, dtype=torch.long, device=self.device)  # each record's frame
        # Slots [0, size) hold records (size grows to capacity, then stays); head is the next slot to
        # write, which is the oldest record once full.
        self._head = 0
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def stored(self) -> TrainingRecords:
        """The records held, oldest first."""
        return TrainingRecords._unpack(self._data[self._ring_slots()])

    def started(self) -> Tensor:
        """``(len,)`` the frame each held record's training path started in (-1: unknown), oldest first."""
        return self._started[self._ring_slots()]

    def push(self, records: TrainingRecords, valid: Tensor, started: int | Tensor = -1) -> None:
        """Store the records where the bool ``valid`` ``(N,)`` is True, in order, overwriting the oldest; each is
        marked with the frame its training path started in (``started``: one for all or ``(N,)``; -1 unknown)."""
        new = records._packed()[valid][-self.capacity:]
        k = new.shape[0]
        slots = (torch.arange(k, device=self.device) + self._head) % self.capacity
        self._data.index_copy_(0, slots, new.to(self._data))
        frames = torch.as_tensor(started, dtype=torch.long, device=self.device).expand(valid.shape[0])
        self._started.index_copy_(0, slots, frames[valid][-self.capacity:])
        self._head = (self._head + k) % self.capacity
        self._size = min(self._size + k, self.capacity)

    def fill(self, records: TrainingRecords, valid: Tensor, gen: torch.Generator) -> TrainingRecords:
        """``records`` with every invalid record replaced by a uniformly random stored record.

        Keeps the batch size and the position of valid records. While the buffer is empty there is
        nothing to draw from: returns only the valid records (a shorter, possibly empty batch).
        Does not store anything; call :meth:`push` afterwards.
        """
        packed = records._packed()
        if self._size == 0:
            return TrainingRecords._unpack(packed[valid])
        slots = torch.randint(self._size, (packed.shape[0],), generator=gen, device=self.device)
        return TrainingRecords._unpack(torch.where(valid[:, None], packed, self._data[slots]))

    def state_dict(self) -> dict[str, Any]:
        """The stored records in their slots, and the write position, for checkpoints: :meth:`fill` draws slots, so an
        exact resume needs the layout, not just the records (a full ring's oldest record is not in slot 0)."""
        return {"capacity": self.capacity, "records": self._data[:self._size].cpu(), "head": self._head,
                "started": self._started[:self._size].cpu()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict` of a buffer with the same capacity."""
        if state["capacity"] != self.capacity:
            raise ConfigError(f"renderer.training.ring_buffer holds {self.capacity} records, the checkpoint's ring "
                              f"{state['capacity']}: resume with renderer.training.ring_buffer={state['capacity']}")
        records = state["records"].to(self._data)
        self._data.zero_()
        self._data[:records.shape[0]] = records
        self._started.fill_(-1)
        if "started" in state:  # older checkpoints do not mark the records
            self._started[:records.shape[0]] = state["started"].to(self._started)
        self._size = records.shape[0]
        self._head = int(state.get("head", self._size % self.capacity))  # older checkpoints: oldest first

    def _ring_slots(self) -> Tensor:
        """The occupied slots, oldest record first."""
        return (torch.arange(self._size, device=self.device) + self._head - self._size) % self.capacity
