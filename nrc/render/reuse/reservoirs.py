"""What the reuse pass resamples: the recorded reuse vertices of a frame (:class:`VertexRecord`), one reservoir per
sample slot (:class:`Reservoirs`), and the end of each slot's initial RIS (:func:`finish_ris`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.program import VertexEvent
from nrc.transport.ris import ris_choice


@dataclass
class VertexRecord:
    """The render paths' reuse vertices of one frame (or ``pt`` pass), one row per sample slot
    ``pixel x spp + sample``: position ``x``, incoming unit direction ``d``, throughput x albedo ``beta``
    (``(N, 3)``), ``mis`` (the path goes on from it: the environment's MIS applies) and ``valid`` (``(N,)``).
    A watcher of the wavefront's vertex passes (:meth:`record` of a
    :class:`~nrc.render.wavefront.program.VertexEvent`)."""

    vertex: int
    albedo: float
    x: Tensor
    d: Tensor
    beta: Tensor
    mis: Tensor
    valid: Tensor

    @classmethod
    def empty(cls, n: int, vertex: int, albedo: float, device: torch.device) -> VertexRecord:
        z3 = torch.zeros(n, 3, device=device)
        zb = torch.zeros(n, dtype=torch.bool, device=device)
        return cls(vertex, float(albedo), z3, z3.clone(), z3.clone(), zb, zb.clone())

    @property
    def n(self) -> int:
        return self.x.shape[0]

    def record(self, ev: VertexEvent) -> None:
        """Record the reuse vertices of a vertex pass: render samples at vertex :attr:`vertex` whose direct light
        is estimated there (the renderer's vertex program left that estimate to this pass)."""
        at = (ev.n == self.vertex - 1) & (ev.sample >= 0)
        idx = (at & ev.nee).nonzero().squeeze(1)
        if not len(idx):
            return
        slot = ev.sample[idx]
        mis, scale = ev.mis[idx], ev.scale[idx]
        self.x[slot] = ev.x[idx]
        self.d[slot] = ev.d[idx]
        self.beta[slot] = ev.beta[idx] * self.albedo * scale[:, None]
        self.mis[slot] = mis
        self.valid[slot] = True


class Rows:
    """Row-wise tensors of a dataclass: ``take`` rows, ``state_dict`` / ``from_state`` for checkpoints."""

    SAMPLE: tuple[str, ...] = ()  # the fields that make up the kept sample (moved by resampling)

    def take(self, idx: Tensor) -> Any:
        return type(self)(*(getattr(self, f.name)[idx] for f in fields(self)))

    def state_dict(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name).cpu() for f in fields(self)}

    @classmethod
    def from_state(cls, state: dict[str, Tensor], device: torch.device) -> Any:
        return cls(**{f.name: state[f.name].to(device) for f in fields(cls)})

    def resampled(self, inputs: list, sel: Tensor, W: Tensor, M: Tensor) -> Any:
        """These receivers with the sample of ``inputs[sel]`` (row-wise), weight ``W`` and confidence ``M``."""
        return replace(self, W=W, M=M, **{k: gather([getattr(r, k) for r in inputs], sel) for k in self.SAMPLE})


@dataclass
class Reservoirs(Rows):
    """One reservoir per sample slot: the kept sample ``(light (N,) int64, omega (N, 3))``, its unbiased
    contribution weight ``W`` and confidence ``M`` (``(N,)``), and the vertex it belongs to (``x``, ``d``,
    ``mis``, ``valid``)."""

    light: Tensor
    omega: Tensor
    W: Tensor
    M: Tensor
    x: Tensor
    d: Tensor
    mis: Tensor
    valid: Tensor
    SAMPLE = ("light", "omega")

    @property
    def anchor(self) -> Tensor:
        """The world point temporal reuse projects into the previous camera."""
        return self.x


def finish_ris(ws: list[Tensor], ps: list[Tensor], u: Tensor, valid: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The end of an initial RIS over ``m = len(ws)`` candidates per row: ``ws`` their resampling weights
    ``p_hat / p_src``, ``ps`` their targets ``p_hat``, ``u`` ``(N,)`` the choice. Returns the chosen index
    ``(N,)``, the contribution weight ``W = sum w / (m p_hat(chosen))`` (0 where the row is invalid or nothing
    has weight) and the confidence ``M = m`` (0 on invalid rows)."""
    m = len(ws)
    sel, total = ris_choice(ws, u)
    ph = gather(ps, sel)
    ok = valid & (total > 0) & (ph > 0)
    W = torch.where(ok, total / (m * ph).clamp(min=1e-30), torch.zeros_like(total))
    M = torch.where(valid, torch.full_like(total, float(m)), torch.zeros_like(total))
    return sel, W, M


def gather(values: list[Tensor], sel: Tensor) -> Tensor:
    """``values[sel[n]][n]`` for each row ``n`` (``(N,)`` or ``(N, 3)`` values)."""
    return torch.stack(values, 1)[torch.arange(len(sel), device=sel.device), sel]
