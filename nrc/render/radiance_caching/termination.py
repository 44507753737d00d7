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

The rules run in the transport step's vertex (:meth:`nrc.render.wavefront.step.Transport.vertex`), whose
numbers come from this dataclass through the step's parameter vector (changing them recompiles nothing).

Termination never changes the estimator's expectation when the cache is exact (the cached value at a
vertex is the expected remainder of the path), so neither rule reweights the throughput.
"""

from __future__ import annotations

from dataclasses import dataclass

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
