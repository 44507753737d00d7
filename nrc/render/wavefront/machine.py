"""Running the transport step eagerly or compiled, once per process and structure (``renderer.backend``).

A :class:`Machine` wraps the two step functions of a :class:`~nrc.render.wavefront.step.Transport`. With
``compile=True`` each is ``torch.compile``'d with a dynamic slot dimension and dynamic grid / majorant-table
lengths; the scene's numbers arrive in the ``P`` tensor (:class:`SceneInputs`), so one compiled graph serves
every scene of the same structure: a sweep over density scale, g, albedo, lights, camera or another VDB file
compiles once per process, and later processes load the kernels from the persistent inductor cache
(:func:`inductor_cache_dir`). Machines are kept per process by :func:`machine_for` (keyed by the step's
:attr:`~nrc.render.wavefront.step.Transport.key` and device); a marker file per structure in the cache
directory tells ``backend=auto`` that a compile would be a cache load (:func:`is_cached`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from nrc.render.wavefront.step import Transport

log = logging.getLogger(__name__)
HEARTBEAT_S = 20.0  # a compile says it is still going this often
MIN_SLOTS = 64  # compaction never goes below this (dynamic-shape kernels specialise sizes 0 and 1)
# Inductor options. The tracking step is vectorised (SIMD C++); the vertex, which runs on the few percent of
# slots at a real collision, is not: its vector code generation took about half of a cold compile and bought
# nothing measurable (docs/benchmarks.md). GPUs (Triton) ignore the C++ options.
# The C++ kernels are specialised on the process's thread count (part of the cache key): a process with
# another count (a joblib worker gets cores / n_jobs) compiles its own entry once. (cpp.dynamic_threads would
# avoid that, but its kernels were not reused from the cache at all in torch 2.13.)
TRACK_OPTIONS = {"assert_indirect_indexing": False}
VERTEX_OPTIONS = {"assert_indirect_indexing": False, "cpp.vec_isa_ok": False}
RECOMPILE_LIMIT = 64  # structures per process before Dynamo would fall back to eager (default 8)


@dataclass
class SceneInputs:
    """The tensors a step takes besides the state: ``P`` (scene numbers), the flat density grid and the flat
    majorant table (each padded by one zero so that no length is 0 or 1, which dynamic shapes specialise)."""

    P: Tensor
    density: Tensor
    majorant: Tensor

    @staticmethod
    def build(P: Tensor, density: Tensor, majorant: Tensor) -> SceneInputs:
        pad = lambda t: torch.cat([t.reshape(-1).float(), t.new_zeros(1)]).contiguous()  # noqa: E731
        return SceneInputs(P.contiguous(), pad(density), pad(majorant))


def _default_inductor_cache() -> str:
    return str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nrc" / "inductor")


# Set on import, before anything compiles: torch sets the variable itself (to /tmp/torchinductor_<user>) the first
# time it compiles anything (the NRC cache's network, say), and every later compile follows it.
os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", _default_inductor_cache())


def inductor_cache_dir() -> Path:
    """The persistent compile cache: ``$TORCHINDUCTOR_CACHE_DIR``, set to ``~/.cache/nrc/inductor`` when unset."""
    path = Path(os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", _default_inductor_cache()))
    path.mkdir(parents=True, exist_ok=True)
    return path


def _marker(step: Transport, device: torch.device) -> Path:
    # CPU kernels are specialised on the thread count (see TRACK_OPTIONS): a joblib worker with fewer threads than
    # the process that compiled finds no kernels in the cache, so the marker names the count too
    threads = torch.get_num_threads() if device.type == "cpu" else 0
    text = repr((step.structure, str(device.type), torch.__version__, threads))
    return inductor_cache_dir() / f"nrc-{hashlib.sha1(text.encode()).hexdigest()[:16]}.compiled"


def is_cached(step: Transport, device: torch.device) -> bool:
    """A compiled machine of this structure was built before with this cache and, on the CPU, this thread count
    (a compile is a cache load)."""
    return _marker(step, device).exists()


def compiled_graphs() -> int:
    """Graphs Dynamo has compiled in this process (a sweep that recompiles nothing keeps this constant)."""
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"])


def _compile(fn: Any, options: dict[str, Any]) -> Any:
    """``torch.compile`` of a step ``(F, I, P, density, majorant) -> (F, I)``: dynamic slot count and grid /
    table lengths (one graph for all), indices clamped in the code (no bounds assertions in the gathers)."""
    compiled = torch.compile(fn, dynamic=False, fullgraph=True, options=options)

    def run(F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
        torch._dynamo.mark_dynamic(F, 1)
        torch._dynamo.mark_dynamic(I, 1)
        torch._dynamo.mark_dynamic(density, 0)
        torch._dynamo.mark_dynamic(majorant, 0)
        return compiled(F, I, P, density, majorant)

    return run


class Machine:
    """The step functions of one structure, compiled or eager (the identical code).

    ``track(F, I, inputs)`` runs ``steps_per_call`` tracking steps; ``vertex(F, I, inputs)`` the vertex of the
    given slots (sizes below 2 run eagerly: dynamic shapes specialise them).
    """

    def __init__(self, step: Transport, steps_per_call: int, compile: bool, device: torch.device) -> None:
        self.step, self.steps_per_call, self.compiled, self.device = step, steps_per_call, compile, device

        def track(F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
            for _ in range(steps_per_call):
                F, I = step.track(F, I, P, density, majorant)
            return F, I

        self._track_eager, self._vertex_eager = track, step.vertex
        if compile:
            inductor_cache_dir()
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
            self._track, self._vertex = _compile(track, TRACK_OPTIONS), _compile(step.vertex, VERTEX_OPTIONS)
        else:
            self._track, self._vertex = track, step.vertex
        self.startup_s: float | None = None if compile else 0.0
        self.cache_hit: bool | None = None

    def track(self, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        fn = self._track if F.shape[1] >= 2 else self._track_eager
        return fn(F, I, inputs.P, inputs.density, inputs.majorant)

    def vertex(self, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        fn = self._vertex if F.shape[1] >= 2 else self._vertex_eager
        return fn(F, I, inputs.P, inputs.density, inputs.majorant)

    def warm_up(self, inputs: SceneInputs, slots: int) -> float:
        """Compile (or load from the cache) by calls on idle working sets (inductor picks its parallelisation
        from the sizes it sees first); returns the seconds it took (0 when already done)."""
        if self.startup_s is not None:
            return 0.0
        marker = _marker(self.step, self.device)
        self.cache_hit = marker.exists()
        where = inductor_cache_dir()
        if self.cache_hit:
            log.info("loading the compiled transport step from %s (a few seconds)", where)
        else:
            log.info("compiling the transport step for this light / estimator structure on %s: once, about 1-3 "
                     "minutes on 2 CPU cores; it is kept in %s, so later runs of any scene of this structure load "
                     "it in seconds (renderer.backend=eager skips the compile)", self.device.type, where)
        done = threading.Event()
        t0 = time.perf_counter()

        def heartbeat() -> None:
            while not done.wait(HEARTBEAT_S):
                log.info("... still %s the transport step (%.0f s)", "loading" if self.cache_hit else "compiling",
                         time.perf_counter() - t0)

        threading.Thread(target=heartbeat, daemon=True).start()
        try:
            layout = self.step.layout
            F, I = layout.zeros(max(slots, MIN_SLOTS), self.device)
            self.track(F, I, inputs)
            k = max(F.shape[1] // 16, 2)
            self.vertex(F[:, :k].contiguous(), I[:, :k].contiguous(), inputs)
        finally:
            done.set()
        self.startup_s = time.perf_counter() - t0
        marker.touch()
        if not self.cache_hit:
            log.info("compiled the transport step in %.0f s (cached for the next run)", self.startup_s)
        return self.startup_s


MACHINE_CACHE = 16  # machines kept per process
_machines: list[tuple[tuple[Any, ...], Machine]] = []


def machine_for(step: Transport, steps_per_call: int, compile: bool, device: torch.device) -> Machine:
    """The process's machine for ``step``'s structure (built on first use): every tracer of the same structure
    shares it, whatever its scene numbers, grid, camera, spp or seed."""
    key = (step.key, steps_per_call, compile, str(device))
    for i, (k, machine) in enumerate(_machines):
        if k == key:
            _machines.append(_machines.pop(i))
            return machine
    machine = Machine(step, steps_per_call, compile, device)
    _machines.append((key, machine))
    del _machines[:-MACHINE_CACHE]
    return machine


def compiled_machine_ready(step: Transport, steps_per_call: int, device: torch.device) -> bool:
    """This process already holds a warm compiled machine of ``step``'s structure."""
    key = (step.key, steps_per_call, True, str(device))
    return any(k == key and m.startup_s is not None for k, m in _machines)
