"""Axis-aligned world box of a volume and batched ray/box clipping."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Box:
    """An axis-aligned box ``[lo, hi]`` in world units (both ``(3,)`` float32 tensors)."""

    lo: Tensor
    hi: Tensor

    @property
    def extent(self) -> Tensor:
        """Edge lengths ``hi - lo``, world units, shape ``(3,)``."""
        return self.hi - self.lo

    @property
    def center(self) -> Tensor:
        return 0.5 * (self.lo + self.hi)

    def contains(self, x: Tensor) -> Tensor:
        """Boolean ``(N,)``: points ``x`` ``(N, 3)`` inside or on the box."""
        return ((x >= self.lo) & (x <= self.hi)).all(dim=-1)

    def normalize(self, x: Tensor) -> Tensor:
        """Map world points ``(N, 3)`` to box coordinates in ``[0, 1]^3`` (not clamped)."""
        return (x - self.lo) / self.extent

    def intersect(self, origin: Tensor, direction: Tensor) -> tuple[Tensor, Tensor]:
        """Clip rays to the box (slab test).

        Args:
            origin: ``(N, 3)`` ray origins, world units.
            direction: ``(N, 3)`` ray directions (need not be unit; ``t`` is in units of ``|direction|``).

        Returns:
            ``(t_near, t_far)``, each ``(N,)``, with ``0 <= t_near <= t_far``. A ray misses the box (or the
            box lies behind it) exactly when ``t_near == t_far``, and then both are 0. Both are finite for
            every ray with a non-zero direction (no inf or NaN for direction components that are zero).
        """
        inv = 1.0 / direction  # +-inf for zero components, handled below
        t0 = (self.lo - origin) * inv
        t1 = (self.hi - origin) * inv
        tmin = torch.minimum(t0, t1)
        tmax = torch.maximum(t0, t1)
        # A zero direction component gives (lo-o)*inf: +-inf when o is off that slab, NaN when o is on a face.
        # Inside the slab the axis must not restrict the interval; outside it the ray misses.
        zero = direction == 0
        inside_slab = (origin >= self.lo) & (origin <= self.hi)
        big = torch.finfo(origin.dtype).max
        tmin = torch.where(zero, torch.where(inside_slab, -big, big), tmin)
        tmax = torch.where(zero, torch.where(inside_slab, big, -big), tmax)
        t_near = tmin.amax(dim=-1).clamp(min=0.0)
        t_far = tmax.amin(dim=-1)
        hit = t_far > t_near
        zero_t = torch.zeros_like(t_near)
        return torch.where(hit, t_near, zero_t), torch.where(hit, t_far, zero_t)


def box_exit(lo: tuple, hi: tuple, o: tuple[Tensor, Tensor, Tensor], d: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """``t_far`` ``(S,)`` of :meth:`Box.intersect` for rays ``o + t d`` given per component (three ``(S,)``
    tensors each; ``lo``/``hi`` Python numbers or 0-d tensors): 0 when the ray misses the box or it lies
    behind. Elementwise only, so a compiler fuses it into its caller."""
    big = torch.finfo(torch.float32).max
    t_near, t_far = None, None
    for a in range(3):
        inv = 1.0 / d[a]
        t0, t1 = (lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv
        zero = d[a] == 0
        inside = (o[a] >= lo[a]) & (o[a] <= hi[a])
        tmin = torch.where(zero, torch.where(inside, -big, big), torch.minimum(t0, t1))
        tmax = torch.where(zero, torch.where(inside, big, -big), torch.maximum(t0, t1))
        t_near = tmin if t_near is None else torch.maximum(t_near, tmin)
        t_far = tmax if t_far is None else torch.minimum(t_far, tmax)
    t_near = t_near.clamp(min=0.0)
    return torch.where(t_far > t_near, t_far, torch.zeros_like(t_far))
