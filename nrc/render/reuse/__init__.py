"""Reservoir reuse (ReSTIR) of light samples across pixels and frames, for ``pt`` and ``nrc``
(``renderer.reuse``): the pass itself (:mod:`~nrc.render.reuse.reservoirs`) and its hook in the transport
step (:mod:`~nrc.render.reuse.hook`)."""

from nrc.render.reuse.hook import ReuseHook
from nrc.render.reuse.reservoirs import (REUSE_DOMAINS, REUSE_MIS, REUSE_MODES, REUSE_TARGETS, DistanceReuse,
                                         ExtinctionTable, ReservoirReuse, Reservoirs, ReuseSettings, VertexRecord,
                                         make_reuse)

__all__ = ["REUSE_DOMAINS", "REUSE_MIS", "REUSE_MODES", "REUSE_TARGETS", "DistanceReuse", "ExtinctionTable",
           "ReservoirReuse", "ReuseHook", "Reservoirs", "ReuseSettings", "VertexRecord", "make_reuse"]
