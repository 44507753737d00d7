"""Reservoir reuse (ReSTIR) of light samples across pixels and frames, for ``pt`` and ``nrc`` (``renderer.reuse``).

By concept: the settings and what they ask for (:mod:`~nrc.render.reuse.settings`); the hook in the transport step
(:mod:`~nrc.render.reuse.hook`); the recorded vertices and the reservoirs (:mod:`~nrc.render.reuse.reservoirs`);
the pass, light domain (:mod:`~nrc.render.reuse.light_reuse`) and distance domain
(:mod:`~nrc.render.reuse.distance_reuse`); extinction along rays for their targets and estimators
(:mod:`~nrc.render.reuse.extinction`). The estimator: ``docs/path_tracer.md``, "Reservoir reuse".
"""

from nrc.render.reuse.distance_reuse import DistanceReuse
from nrc.render.reuse.extinction import ExtinctionTable
from nrc.render.reuse.hook import ReuseHook
from nrc.render.reuse.light_reuse import ReservoirReuse
from nrc.render.reuse.reservoirs import Reservoirs, VertexRecord
from nrc.render.reuse.settings import REUSE_DOMAINS, REUSE_MIS, REUSE_MODES, REUSE_TARGETS, ReuseSettings, make_reuse

__all__ = ["REUSE_DOMAINS", "REUSE_MIS", "REUSE_MODES", "REUSE_TARGETS", "DistanceReuse", "ExtinctionTable",
           "ReservoirReuse", "ReuseHook", "Reservoirs", "ReuseSettings", "VertexRecord", "make_reuse"]
