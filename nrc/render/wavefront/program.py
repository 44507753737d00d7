"""What a renderer does at a vertex, as the core sees it: a vertex program (inside the step) and a collector
(around it, in the driver).

The core (:mod:`~nrc.render.wavefront.step`, :mod:`~nrc.render.wavefront.driver`) schedules: refill, tracking,
the vertex pass, harvest, compaction, the queues. It scatters every path that goes on (throughput x albedo,
next-event estimate, throughput roulette, phase-sampled continuation) and knows nothing of what a renderer adds.
A renderer adds it through two objects it owns:

* a :class:`VertexProgram` (run inside the step, eager or compiled from the same code): its state fields, its
  accumulator rows, its numbers in ``P``, its random lanes, and :meth:`VertexProgram.at_vertex`, which returns a
  :class:`Decision` with named fields (does the path go on, does the vertex make a next-event estimate, with which
  throughput and MIS, does the next segment count the environment); its ``hooks`` (vertex-level features shared
  by renderers, such as reservoir reuse) adjust that decision in turn;
* a :class:`Collector` (run by the driver): which accumulator rows a slot's contributions go to, and what the
  renderer keeps from harvested slots and from each vertex pass; its ``watchers`` receive every vertex pass as a
  documented :class:`VertexEvent`.

The base classes are ``renderer=pt``'s: every vertex scatters, one accumulator row (the pixel), nothing
collected. ``renderer=nrc``'s live in :mod:`nrc.render.radiance_caching.vertex`; reservoir reuse's in
:mod:`nrc.render.reuse`.

A program's code is part of the compiled step: its module must be listed in
:data:`nrc.render.compile_cache.STEP_SOURCES` (the compile cache is keyed by those files), and
:attr:`VertexProgram.structure` must hold everything its code depends on; its numbers travel in ``P``
(:meth:`VertexProgram.param_values`), never as attributes the step reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor


@dataclass
class Decision:
    """What happens at the vertex of each slot (``(S,)`` bool masks, throughputs as 3-tuples of ``(S,)``)."""

    go: Tensor
    """The path scatters here and goes on (``False``: it ends here, handed to the collector as a query)."""
    nee: Tensor
    """The vertex makes a next-event estimate."""
    mis: Tensor
    """That estimate is MIS-weighted against phase sampling of the environment (the path goes on to find it)."""
    nee_beta: tuple
    """Throughput of the next-event estimate (albedo included)."""
    beta: tuple
    """Throughput of the continuation (albedo included; before the throughput roulette)."""
    skip_env: Tensor | None = None
    """The next segment's escape does not count the environment (its direct light was estimated otherwise);
    ``None``: every escape counts it. Kept in the state field ``skip_env``, which exists where the program
    declares :attr:`VertexProgram.skips_env`."""
    env_by_phase: Tensor | None = None
    """``(S,)`` bool, true with probability 1/2: the step applies it where the estimate is not MIS-weighted (``mis``
    False) at a vertex the path ends at (``go`` False) and the light sample is the uniform sky's, whose direction
    is then drawn by phase sampling instead of by the sky (a one-sample MIS of the two, balance heuristic);
    ``None``: light sampling alone."""
    shadow_row: Tensor | None = None
    """``(S,)`` the slot's ``L`` row that the next-event estimate's shadow ray adds to when it ends (programs with
    several rows; kept in the state field ``srow``); ``None``: the program's :meth:`VertexProgram.row` of the slot
    after the vertex."""


class VertexProgram:
    """``renderer=pt``'s vertex: every path scatters, one accumulator row (see the module docstring).

    Args:
        hooks: vertex-level features applied after :meth:`at_vertex`, in order (each has ``structure``,
            ``adjust(decision, s, n_s, render)`` and, where it may set :attr:`Decision.skip_env`, ``skips_env``).
    """

    rows = 1  # accumulator rows per slot (the slot's ``L`` has ``3 rows`` floats)
    float_fields: tuple[tuple[str, int], ...] = ()  # extra float state fields (name, width)
    int_fields: tuple[str, ...] = ()  # extra integer state fields
    param_names: tuple[str, ...] = ()  # the program's numbers in ``P``, in order
    lanes = 0  # random lanes of the vertex draw the program uses (after the core's)
    own_skips_env = False  # at_vertex may set Decision.skip_env

    def __init__(self, hooks: tuple = ()) -> None:
        self.hooks = tuple(hooks)

    @property
    def structure(self) -> tuple[Any, ...]:
        """Everything the program's step code depends on, as plain values (part of the compile cache's key)."""
        return ("pt", *(h.structure for h in self.hooks))

    @property
    def fused_tail(self) -> bool:
        """The driver's tail may fuse this program's vertex into the tracking step (:meth:`Transport.advance
        <nrc.render.wavefront.step.Transport.advance>`): nothing is kept of its vertex passes (``pt`` without
        hooks; a hook's watcher records them)."""
        return not self.hooks

    @property
    def skips_env(self) -> bool:
        """The program or one of its hooks may set :attr:`Decision.skip_env` (the state then has the field)."""
        return bool(self.own_skips_env) or any(getattr(h, "skips_env", False) for h in self.hooks)

    def param_values(self, **frame: Any) -> list[float]:
        """The values of :attr:`param_names` (``frame``: numbers that change from frame to frame)."""
        return []

    def row(self, s: Any) -> Tensor | None:
        """Accumulator row ``(S,)`` of each slot's current segment (``None``: row 0)."""
        return None

    def render_path(self, s: Any) -> Tensor | None:
        """``(S,)`` bool: the slot holds a path whose light goes to the image (``None``: every slot)."""
        return None

    def at_vertex(self, s: Any, n_s: Tensor, beta_s: tuple, albedo: Tensor, prm: dict[str, Tensor],
                  u: list[Tensor]) -> Decision:
        """The decision at vertex ``n_s`` (``beta_s``: the throughput x albedo; ``prm``: the program's ``P``
        numbers by name; ``u``: its :attr:`lanes` random lanes). May update the program's state fields in ``s``."""
        go = torch.ones_like(n_s, dtype=torch.bool)
        return Decision(go=go, nee=go, mis=go, nee_beta=beta_s, beta=beta_s)

    def decide(self, s: Any, n_s: Tensor, beta_s: tuple, albedo: Tensor, prm: dict[str, Tensor],
               u: list[Tensor]) -> Decision:
        """:meth:`at_vertex`, then the hooks."""
        d = self.at_vertex(s, n_s, beta_s, albedo, prm, u)
        for hook in self.hooks:
            d = hook.adjust(d, s, n_s, self.render_path(s))
        return d


@dataclass
class VertexEvent:
    """One vertex pass, as watchers see it (``K`` slots; tensors are views where they can be).

    Attributes:
        n: ``(K,)`` real collisions before this vertex (the vertex is number ``n + 1``).
        sample: ``(K,)`` the render sample's id in the frame's image (pt: the pixel); -1 for paths whose light
            does not go to the image (NRC's training paths).
        x: ``(K, 3)`` the vertex.
        d: ``(K, 3)`` the incoming direction.
        beta: ``(K, 3)`` the throughput arriving at the vertex (before its albedo).
        nee: ``(K,)`` the vertex's direct light is to be estimated here.
        mis: ``(K,)`` that estimate is MIS-weighted against phase sampling (the path goes on).
        scale: ``(K,)`` a factor on that estimate's throughput.
    """

    n: Tensor
    sample: Tensor
    x: Tensor
    d: Tensor
    beta: Tensor
    nee: Tensor
    mis: Tensor
    scale: Tensor


class Collector:
    """``renderer=pt``'s collector: every contribution goes to the slot's ``dest`` (the pixel); nothing is kept.

    Args:
        watchers: objects with ``record(event: VertexEvent)``, called at every vertex pass.
    """

    def __init__(self, watchers: tuple = ()) -> None:
        self.watchers = tuple(w for w in watchers if w is not None)

    @property
    def needs_vertex_passes(self) -> bool:
        """The collector keeps something of every vertex pass (:meth:`vertex_pass`): the driver's tail cannot fuse
        the vertex into the tracking step (``pt``: when a watcher, the reuse pass's record, is attached)."""
        return bool(self.watchers)

    def rows(self, ly: Any, I: Tensor, j: Tensor | int) -> Tensor:
        """Accumulator index of row ``j`` (per slot, one for all, or ``(R, 1)``: rows ``R`` of every slot, giving
        ``(R, K)``) of the given slots ``I`` (``K`` columns)."""
        dest = I[ly.i("dest")]
        return dest.expand(j.shape[0], -1) if isinstance(j, Tensor) and j.dim() == 2 else dest

    def current_rows(self, ly: Any, I: Tensor) -> Tensor:
        """Accumulator index of the given slots' current segment."""
        return self.rows(ly, I, 0)

    def direct_rows(self, ly: Any, I: Tensor) -> Tensor:
        """Accumulator index of the given slots' direct light at their current vertex (next-event estimate, the
        MIS-weighted environment of its sampled direction)."""
        return self.current_rows(ly, I)

    def shadow_rows(self, ly: Any, I: Tensor, pass_info: Any, qd: Tensor) -> Tensor:
        """Rows of the next-event requests ``qd`` (indices into the vertex pass) of slots ``I``."""
        return self.direct_rows(ly, I)

    def starts_segment(self, ly: Any, I: Tensor) -> Tensor | None:
        """``(K,)`` bool: the slots' new segments take part in segment estimators (equi-angular); ``None``: all."""
        return None

    def harvest(self, ly: Any, F: Tensor, I: Tensor, flight: Tensor) -> None:
        """Finished slots ``(F, I)`` (their rows already in the accumulator)."""

    def after_advance(self, ly: Any, F: Tensor, I: Tensor) -> None:
        """After each fused call of the driver's tail (:meth:`Machine.advance
        <nrc.render.wavefront.machine.Machine.advance>`, which ran the vertices its slots reached without a vertex
        pass): what the collector keeps of them from the state (``pt``: nothing; ``nrc``: the training records)."""

    def after_advance_ahead(self, ly: Any, I: Tensor) -> bool:
        """Whether :meth:`after_advance` can still find something in the live slots ``I`` (checked after it ran;
        once ``False`` the driver's tail stops calling it, since a tail starts no new path)."""
        return False

    def vertex_pass(self, ly: Any, F_in: Tensor, I_in: Tensor, F_out: Tensor, I_out: Tensor) -> Any:
        """The slots of a vertex pass, before and after the step; returns what :meth:`shadow_rows` needs."""
        if self.watchers:
            event = self.event(ly, F_in, I_in, F_out, I_out)
            for w in self.watchers:
                w.record(event)
        return None

    def event(self, ly: Any, F_in: Tensor, I_in: Tensor, F_out: Tensor, I_out: Tensor) -> VertexEvent:
        """The documented record of a vertex pass (every slot scatters and estimates its direct light)."""
        n = I_in[ly.i("n")]
        yes = torch.ones_like(n, dtype=torch.bool)
        return VertexEvent(n=n, sample=I_in[ly.i("dest")], x=F_out[ly.f("o")].T, d=F_in[ly.f("d")].T,
                           beta=F_in[ly.f("beta")].T, nee=yes, mis=yes, scale=torch.ones(len(n), device=F_in.device))
