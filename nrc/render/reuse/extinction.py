"""Extinction along rays for the reuse pass's own estimators: the targets' deterministic transmittance
(:class:`CoarseTransmittance`) and per-ray extinction tables (:class:`ExtinctionTable`), the distance domain's
source and the control of its residual ratio tracking (``docs/path_tracer.md``, "Distance reuse").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.render.reuse.reservoirs import Rows


class CoarseTransmittance:
    """A deterministic approximation of the transmittance for the reuse targets (as Lin et al. 2021 put a
    coarse-grid transmittance into theirs): the density averaged into at most ``cells^3`` cells (nearest cell;
    ``cells <= 0``: the full-resolution grid, trilinear), marched in ``steps`` equal steps
    (:meth:`ExtinctionTable.march`, midpoints). Always positive, so a target that multiplies by it keeps the
    support of the unshadowed one (the estimate stays unbiased); cost ``steps`` lookups a ray.

    Args:
        grid: the :class:`~nrc.volume.grid.DensityGrid`.
        cells: cells per axis at most (``<= 0``: no averaging); steps: march steps.
    """

    def __init__(self, grid: Any, cells: int = 32, steps: int = 16) -> None:
        self.steps = steps
        self.sigma_at = grid.sigma_t
        if cells > 0:
            size = tuple(min(int(n), cells) for n in grid.shape)
            sigma = torch.nn.functional.adaptive_avg_pool3d(grid.density[None, None], size)[0, 0] * grid.density_scale
            self.sigma = sigma.reshape(-1).contiguous()
            self.size = torch.tensor(size, device=grid.device)
            self.lo, self.extent = grid.box.lo, grid.box.hi - grid.box.lo
            self.sigma_at = self._cell_sigma

    def __call__(self, x: Tensor, wi: Tensor, t1: Tensor) -> Tensor:
        """``T`` ``(N,)`` from ``x`` along unit ``wi`` over ``[0, t1]`` (``(N, 3)``, ``(N, 3)``, ``(N,)``)."""
        return torch.exp(-ExtinctionTable.march(self.sigma_at, x, wi, torch.zeros_like(t1), t1, self.steps).total())

    def _cell_sigma(self, p: Tensor) -> Tensor:
        """The averaged extinction of the cells holding points ``p`` ``(..., 3)`` (0 outside the box)."""
        s = (p - self.lo) / self.extent
        inside = ((s >= 0) & (s < 1)).all(-1)
        c = torch.minimum((s.clamp(min=0.0) * self.size).long(), self.size - 1)
        flat = (c[..., 0] * self.size[1] + c[..., 1]) * self.size[2] + c[..., 2]
        return torch.where(inside, self.sigma[flat], torch.zeros_like(p[..., 0]))


class _Table:
    """Per-ray extinction tables: rays ``o``, ``d`` ``(N, 3)`` with a span ``[ta, tb]`` ``(N,)``, the extinction
    read at the midpoints of ``S`` equal steps over it, kept as its optical depth at each step's end ``cum``
    ``(N, S)`` (a prefix sum, built once a ray; the step's extinction is its difference), and ``valid`` ``(N,)``
    (the span is not empty). Piecewise constant: a deterministic control for the distance source, the targets
    and the residual transmittance estimate. Memory: ``S`` floats a ray."""

    def tau(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Along these rays (or the ``rows`` of them) at distances ``t`` ``(N,)``: the table's optical depth from
        ``ta``, its extinction there, and whether ``t`` lies in ``[ta, tb]`` of a valid ray."""
        rows = torch.arange(len(t), device=t.device) if rows is None else rows
        S = self.cum.shape[1]
        ta, tb = self.ta[rows], self.tb[rows]
        h = (tb - ta).clamp(min=1e-30) / S
        k = torch.floor((t - ta) / h).clamp(0, S - 1).long()
        sig_k = self.step_sigma(rows, k, h)
        tau = self.cum[rows, k] - sig_k * ((k + 1).to(t.dtype) * h - (t - ta))
        inside = self.valid[rows] & (t >= ta) & (t <= tb)
        return tau, sig_k, inside

    def step_sigma(self, rows: Tensor, k: Tensor, h: Tensor) -> Tensor:
        """The table's extinction in step ``k`` of ``rows`` (step length ``h``), from the prefix sum."""
        before = torch.where(k > 0, self.cum[rows, (k - 1).clamp(min=0)], torch.zeros_like(h))
        return (self.cum[rows, k] - before) / h

    def total(self) -> Tensor:
        """The table's optical depth of the whole span ``(N,)``."""
        return self.cum[:, -1]

    def transmittance(self, grid: Any, t: Tensor, points: float, gen: torch.Generator) -> Tensor:
        """An unbiased estimate of ``T(ta, t)`` ``(N,)`` on these rays: residual ratio tracking with the table as
        the control, ``exp(-tau_table(t)) prod_i (1 - (sigma_t(x_i) - sig(x_i)) / mu)`` over a Poisson process
        of rate ``mu`` on ``[ta, t]`` (``E prod = exp(-int (sigma_t - sig))`` for any rate, so no bound is
        needed; the relative second moment is ``exp(int (sigma_t - sig)^2 / mu)``, small where the table
        resolves the grid). ``mu = max(points / (t - ta), the table's largest jump between steps)``, at most
        ``4 points / (t - ta)``: ``points`` density lookups a ray on average where the table is fine, up to
        ``4 points`` where it is coarse against the grid (which keeps the factors near ``[0, 2]`` there). Not
        bounded to ``[0, 1]``."""
        tau, _, _ = self.tau(t)
        span = (t - self.ta).clamp(min=0.0)
        S = self.cum.shape[1]
        sig = torch.diff(self.cum, dim=1, prepend=torch.zeros_like(self.cum[:, :1])) * (S / (self.tb - self.ta)
                                                                                          .clamp(min=1e-30))[:, None]
        jump = (sig[:, 1:] - sig[:, :-1]).abs().amax(1) if S > 1 else torch.zeros_like(span)
        base = float(points) / span.clamp(min=1e-30)
        mu = torch.maximum(base, torch.minimum(jump, 4.0 * base))  # about the residual's size, within 4x
        n = torch.poisson(mu * span, generator=gen).long()
        k = int(n.max().item()) if len(n) else 0
        u = torch.rand(len(n), k, generator=gen, device=t.device)
        i, j = (torch.arange(k, device=t.device)[None, :] < n[:, None]).nonzero(as_tuple=True)
        ti = self.ta[i] + u[i, j] * span[i]
        resid = grid.sigma_t(self.o[i] + ti[:, None] * self.d[i]) - self.tau(ti, i)[1]
        factor = torch.ones(len(n), max(k, 1), device=t.device)
        factor[i, j] = 1.0 - resid / mu[i]
        return torch.exp(-tau) * factor.prod(1)


@dataclass
class ExtinctionTable(_Table, Rows):
    """A :class:`_Table` with its rays (shadow segments; the camera rays of
    :class:`~nrc.render.reuse.distance_reuse.DistanceReservoirs`)."""

    o: Tensor
    d: Tensor
    ta: Tensor
    tb: Tensor
    cum: Tensor
    valid: Tensor

    @classmethod
    def march(cls, sigma: Any, o: Tensor, d: Tensor, ta: Tensor, tb: Tensor, steps: int) -> ExtinctionTable:
        """The table of ``steps`` equal steps over ``[ta, tb]`` ``(N,)`` of rays ``o``, ``d``: the extinction
        ``sigma(points (M, 3)) -> (M,)`` (the grid's ``sigma_t``, or :class:`CoarseTransmittance`'s cells) read
        at the steps' midpoints, ``steps`` lookups a ray with a non-empty span."""
        valid = tb > ta
        i = valid.nonzero().squeeze(1)  # empty spans read nothing (their table is 0)
        frac = (torch.arange(steps, device=o.device, dtype=o.dtype) + 0.5) / steps
        tm = ta[i, None] + frac[None, :] * (tb - ta)[i, None]
        sig = sigma((o[i, None, :] + tm[..., None] * d[i, None, :]).reshape(-1, 3)).view(len(i), steps)
        cum = torch.zeros(len(o), steps, device=o.device, dtype=o.dtype)
        cum[i] = torch.cumsum(sig, 1) * ((tb - ta)[i] / steps)[:, None]
        return cls(o, d, ta, tb, cum, valid)
