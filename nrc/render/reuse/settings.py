"""The ``renderer.reuse`` settings (one reader for both renderers) and the pass, hooks and record they ask for.

The estimator: :mod:`nrc.render.reuse.light_reuse` (its steps) and ``docs/path_tracer.md``, "Reservoir reuse" (the
derivation, the MIS weights, the measurements).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from nrc.render.reuse.distance_reuse import DistanceReuse
from nrc.render.reuse.hook import ReuseHook
from nrc.render.reuse.light_reuse import ReservoirReuse
from nrc.render.reuse.reservoirs import VertexRecord

REUSE_MODES = ("none", "spatial", "spatiotemporal")
REUSE_TARGETS = ("unshadowed", "coarse", "fine")
REUSE_MIS = ("pairwise", "balance")
REUSE_DOMAINS = ("light", "distance")


@dataclass(frozen=True)
class ReuseSettings:
    """``renderer.reuse`` (``conf/renderer/shared/wavefront.yaml``, included by both renderers; one reader)."""

    mode: str = "none"
    """``none`` | ``spatial`` | ``spatiotemporal`` (:mod:`nrc.render.reuse.light_reuse`)."""
    neighbors: int = 4
    """Spatial neighbours ``K`` combined per pixel (``>= 0``; the combination costs ``3K + 1`` target
    evaluations with ``mis=pairwise``, ``(K + 1)^2`` with ``balance``). ``0``: no spatial reuse (``spatial``
    is then each pixel's own RIS, the baseline that shows what reuse adds)."""
    radius: float = 10.0
    """Spatial neighbours are drawn uniformly in a ring of 1 to ``radius`` pixels (``>= 1``)."""
    history: float = 20.0
    """Temporal reuse: the previous reservoir's confidence ``M`` is clamped to ``history`` times the initial
    candidates (``> 0``), which bounds how long an old sample can dominate."""
    defer_g: float = 1.0
    """Reuse starts at vertex 2 when ``|g| >= defer_g`` (deferred reuse; ``1``: never, as ``|g| < 1``)."""
    target: str = "unshadowed"
    """The resampling target: ``unshadowed`` (light x phase), ``coarse`` (times
    :class:`~nrc.render.reuse.extinction.CoarseTransmittance` towards the light, the grid averaged into ``32^3``
    cells) or ``fine`` (the same march on the full-resolution grid: 16 trilinear lookups a target evaluation; with
    ``domain=distance`` it is the measured best)."""
    mis: str = "balance"
    """The resampling MIS weights of spatial reuse: ``balance`` (the generalized balance heuristic over all
    inputs, ``(K + 1)^2`` target evaluations) or ``pairwise`` (each neighbour against the receiver, ``3K + 1``).
    Temporal reuse (two inputs): the same. ``balance`` is the default by measurement (``docs/path_tracer.md``)."""

    domain: str = "light"
    """What a reservoir holds: ``light`` (a light sample ``y`` for the pixel's own first vertex, which delta
    tracking placed) or ``distance`` (a pair ``(t, y)``: a distance along the pixel's camera ray and a light
    sample, Lin et al. 2021; the camera ray's single scattering of the sampled lights is then estimated by
    the reservoirs alone, see :class:`DistanceReuse`)."""
    distance_candidates: int = 8
    """``domain=distance``: candidate pairs ``(t, y)`` per pixel in the initial RIS (``>= 1``)."""
    distance_steps: int = 32
    """``domain=distance``: equal steps of the extinction table along each camera ray (``>= 1``), read from the
    full-resolution grid at the step midpoints: the distance source and the targets' transmittance. More
    steps resolve a dense cloud's first mean free path (memory: ``steps`` floats a sample slot)."""

    @classmethod
    def from_config(cls, cfg: Any) -> ReuseSettings:
        """Read the ``reuse`` block of a :class:`nrc.config.ConfigReader` of the ``renderer`` block (every key
        required: the defaults live in ``conf/renderer/shared/wavefront.yaml``)."""
        r = cfg.block("reuse")
        settings = cls(mode=r.get_choice("mode", list(REUSE_MODES)),
                       neighbors=r.get_int("neighbors", lo=0),
                       radius=r.get_float("radius", lo=1.0),
                       history=r.get_float("history", lo=0.0, lo_open=True),
                       defer_g=r.get_float("defer_g", lo=0.0, hi=1.0),
                       target=r.get_choice("target", list(REUSE_TARGETS)),
                       mis=r.get_choice("mis", list(REUSE_MIS)),
                       domain=r.get_choice("domain", list(REUSE_DOMAINS)),
                       distance_candidates=r.get_int("distance_candidates", lo=1),
                       distance_steps=r.get_int("distance_steps", lo=1))
        r.finish()
        return settings

    def vertex(self, g: float) -> int:
        """The render paths' vertex whose next-event estimate is reused (0: none)."""
        if self.mode == "none":
            return 0
        if self.domain == "distance":  # the camera ray's single scattering: always the first vertex's
            return 1
        return 2 if abs(float(g)) >= self.defer_g else 1

    @property
    def light_only(self) -> bool:
        """The reuse vertex's direct light is estimated by light sampling alone (``domain=distance``): the path's
        phase-sampled direction from it does not count the environment it reaches (no MIS there)."""
        return self.mode != "none" and self.domain == "distance"

    def hooks(self, g: float) -> tuple:
        """The hooks of the renderers' vertex programs (none without reuse)."""
        vertex = self.vertex(g)
        return (ReuseHook(vertex, self.light_only),) if vertex else ()

    def record(self, n: int, g: float, albedo: float, device: torch.device) -> VertexRecord | None:
        """An empty record of ``n`` sample slots for the reuse vertices (``None``: nothing to record, no reuse or
        ``domain=distance``)."""
        vertex = self.vertex(g)
        return VertexRecord.empty(n, vertex, albedo, device) if vertex and not self.light_only else None

    def metrics(self, g: float) -> dict[str, Any]:
        return {"reuse": self.mode, "reuse_neighbors": self.neighbors if self.mode != "none" else 0,
                "reuse_radius": self.radius, "reuse_history": self.history, "reuse_vertex": self.vertex(g),
                "reuse_target": self.target, "reuse_mis": self.mis, "reuse_domain": self.domain,
                "reuse_distance_candidates": self.distance_candidates if self.domain == "distance" else 0,
                "reuse_distance_steps": self.distance_steps if self.domain == "distance" else 0}


def make_reuse(settings: ReuseSettings, g: float, spp: int, grid: Any, albedo: float) -> ReservoirReuse | None:
    """The reuse pass ``renderer.reuse`` asks for (``None`` for ``mode=none``)."""
    if settings.mode == "none":
        return None
    if settings.domain == "distance":
        return DistanceReuse(settings, g, spp, grid, albedo)
    return ReservoirReuse(settings, g, spp, grid)
