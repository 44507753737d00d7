"""Reservoir reuse inside the transport step: the render paths' reuse vertex leaves its next-event estimate to the
reuse pass (:mod:`nrc.render.reuse.reservoirs`), which records the vertex by watching the vertex passes.

A hook of a vertex program (:mod:`nrc.render.wavefront.program`), so part of the compiled step: this module is in
:data:`nrc.render.compile_cache.STEP_SOURCES`.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from nrc.render.wavefront.program import Decision


class ReuseHook:
    """At vertex ``vertex`` of a render path: no next-event estimate (the reuse pass makes it); with
    ``light_only`` (``reuse.domain=distance``: the pass estimates all of that vertex's direct light by light
    sampling) the path's phase-sampled segment from there does not count the environment it reaches."""

    def __init__(self, vertex: int, light_only: bool = False) -> None:
        if vertex < 1:
            raise ValueError(f"the reuse vertex must be >= 1, got {vertex}")
        self.vertex, self.light_only = int(vertex), bool(light_only)

    @property
    def structure(self) -> tuple[Any, ...]:
        return ("reuse", self.vertex, "light_only") if self.light_only else ("reuse", self.vertex)

    @property
    def skips_env(self) -> bool:
        """It sets :attr:`Decision.skip_env` (``light_only``): the state keeps the field."""
        return self.light_only

    def adjust(self, d: Decision, s: Any, n_s: Tensor, render: Tensor | None) -> Decision:
        at = n_s == self.vertex
        at = at if render is None else at & render
        d.nee = d.nee & ~at
        if self.light_only:
            d.skip_env = at if d.skip_env is None else d.skip_env | at
        return d
