"""When a render path stops and hands over to the radiance cache (``renderer.termination``).

Both rules are decided at a real scattering vertex, numbered ``n = 1, 2, ...`` along the path:

``count`` (Spindler 2022, Fedotov 2024)
    From vertex ``min_vertices`` on, the path continues with probability ``p_continue`` and otherwise
    terminates into the cache. ``p_continue = 0`` terminates exactly at vertex ``min_vertices``.
``spread`` (Müller et al. 2021, adapted to media as in ``ALGORITHMS.md``)
    ``a0 = |x0 - x1|^2 / (4 pi)`` with ``x0`` the camera and ``x1`` the first vertex; from the second
    vertex on ``sqrt(S) += sqrt(|x_{i-1} - x_i|^2 / p(w_{i-1}))`` with ``p`` the phase pdf of the
    direction that led to ``x_i`` (world units, pdf per steradian). The path terminates at the first
    vertex ``n >= min_vertices`` where ``S^2 > c * a0`` (``spread_c``, 0.01 in Müller et al.).

Termination never changes the estimator's expectation when the cache is exact (the cached value at a
vertex is the expected remainder of the path), so neither rule reweights the throughput.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from nrc.config import ConfigReader

RULES = ("count", "spread")


@dataclass(frozen=True)
class Termination:
    """A validated termination rule (see the module docstring)."""

    rule: str = "count"
    min_vertices: int = 1
    p_continue: float = 0.0
    spread_c: float = 0.01

    @classmethod
    def from_config(cls, cfg: ConfigReader) -> Termination:
        term = cls(
            rule=cfg.get_choice("rule", RULES, "count"),
            min_vertices=cfg.get_int("min_vertices", 1, lo=1),
            p_continue=cfg.get_float("p_continue", 0.0, lo=0.0, hi=1.0, hi_open=True),
            spread_c=cfg.get_float("spread_c", 0.01, lo=0.0, lo_open=True),
        )
        cfg.finish()
        return term

    @staticmethod
    def spread_update(n: Tensor, x: Tensor, x_prev: Tensor, pdf_prev: Tensor, spread: Tensor,
                      a0: Tensor) -> tuple[Tensor, Tensor]:
        """``(spread, a0)`` after reaching vertex ``n`` at ``x`` from ``x_prev`` along a direction of pdf ``pdf_prev``.

        At the first vertex ``x_prev`` is the camera position and the pdf is ignored.
        """
        dist2 = ((x - x_prev) ** 2).sum(-1)
        first = n == 1
        a0 = torch.where(first, dist2 / (4.0 * math.pi), a0)
        grown = spread + torch.sqrt(dist2 / pdf_prev.clamp(min=1e-30))
        return torch.where(first, torch.zeros_like(spread), grown), a0

    def fires(self, n: Tensor, u: Tensor, spread: Tensor, a0: Tensor) -> Tensor:
        """Bool ``(N,)``: the rule says "stop here" at vertex ``n`` (``u`` uniform in [0, 1), count rule only)."""
        eligible = n >= self.min_vertices
        if self.rule == "count":
            return eligible & (u >= self.p_continue)
        return eligible & (spread * spread > self.spread_c * a0)
