"""Running the transport step eagerly or compiled, once per process and structure (``renderer.backend``).

A :class:`Machine` wraps the two step functions of a :class:`~nrc.render.wavefront.step.Transport`. With
``compile=True`` each is compiled with a dynamic slot dimension and dynamic grid / majorant-table lengths; the
scene's numbers arrive in the ``P`` tensor (:class:`SceneInputs`), so one compiled step serves every scene of the
same structure: a sweep over density scale, g, albedo, lights, camera or another VDB file compiles once. On the
CPU the step is compiled ahead of time (``torch.export`` + AOTInductor) into two package files in the persistent
cache (:func:`aot_packages`), which later processes load in milliseconds without importing Dynamo; elsewhere, or
where the export fails, it is ``torch.compile``'d and later processes load its kernels from the persistent
inductor cache (:func:`inductor_cache_dir`) after re-tracing it (seconds). Machines are kept per process by
:func:`machine_for` (keyed by the step's :attr:`~nrc.render.wavefront.step.Transport.key` and device); the
packages, or for ``torch.compile`` a marker file per structure in the cache directory, tell ``backend=auto`` that
a compile would be a cache load (:func:`is_cached`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import signal
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from nrc.errors import failure_line
from nrc.render.compile_cache import default_inductor_cache, inductor_cache_dir, package_sources
from nrc.render.wavefront.graphs import StepGraphs
from nrc.render.wavefront.row_views import plain_row_views
from nrc.render.wavefront.step import Transport
from nrc.transport.rng import uniforms as counter_uniforms

log = logging.getLogger(__name__)
HEARTBEAT_S = 20.0  # a compile says it is still going this often
MIN_SLOTS = 64  # compaction never goes below this (dynamic-shape kernels specialise sizes 0 and 1)
# Inductor options. The tracking step is vectorised (SIMD C++); the vertex, which runs on the few percent of
# slots at a real collision, is not: its vector code generation took about half of a cold compile and bought
# nothing measurable (docs/measurements/speed.md). GPUs (Triton) ignore the C++ options.
# The C++ kernels are specialised on the process's thread count (part of the cache key): a process with
# another count (a joblib worker gets cores / n_jobs) compiles its own entry once. (cpp.dynamic_threads would
# avoid that, but its kernels were not reused from the cache at all in torch 2.13.)
TRACK_OPTIONS = {"assert_indirect_indexing": False}
VERTEX_OPTIONS = {"assert_indirect_indexing": False, "cpp.vec_isa_ok": False}
# The tail's fused step (Transport.advance) runs on a few hundred slots, where a call costs its fixed overhead: one
# thread (no OpenMP region; two threads' barriers between its ~40 loops cost about half of a small call), scalar code.
ADVANCE_OPTIONS = {"assert_indirect_indexing": False, "cpp.vec_isa_ok": False, "cpp.threads": 1}
RECOMPILE_LIMIT = 64  # structures per process before Dynamo would fall back to eager (default 8)
# Where the step is compiled ahead of time into a package (torch.export + AOTInductor) that a later process loads
# in milliseconds without Dynamo (torch.compile re-traces both functions on every start, ~3.4 s, before its cache
# hits): the CPU, measured (docs/measurements/speed.md, "Start-up"). CUDA keeps torch.compile until a GPU run has checked
# the packages there. A step whose export fails falls back to torch.compile.
AOT_DEVICES = ("cpu",)
_aot_built = 0  # AOT packages built by this process (part of compiled_graphs())


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


# Set on import, before anything compiles: torch sets the variable itself (to /tmp/torchinductor_<user>) the first
# time it compiles anything (the NRC cache's network, say), and every later compile follows it.
os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", default_inductor_cache())


def _marker(step: Transport, device: torch.device) -> Path:
    # CPU kernels are specialised on the thread count (see TRACK_OPTIONS): a joblib worker with fewer threads than
    # the process that compiled finds no kernels in the cache, so the marker names the count too
    threads = torch.get_num_threads() if device.type == "cpu" else 0
    text = repr((step.structure, str(device.type), torch.__version__, threads))
    return inductor_cache_dir() / f"nrc-{hashlib.sha1(text.encode()).hexdigest()[:16]}.compiled"


def is_cached(step: Transport, device: torch.device, steps_per_call: int = 1) -> bool:
    """A compiled machine of this structure was built before with this cache and, on the CPU, this thread count
    (a compile is a cache load): its AOT packages where the step has them (:func:`packages_cached`: a marker
    left by an older build or before an edit of the step's sources does not count), else the marker."""
    if aot_packages(step, steps_per_call, device) is not None:
        return packages_cached(step, steps_per_call, device)
    return _marker(step, device).exists()


def packages_cached(step: Transport, steps_per_call: int, device: torch.device) -> bool:
    """All AOT packages of this structure are in the cache: a compile is a load of milliseconds."""
    paths = aot_packages(step, steps_per_call, device)
    return paths is not None and all(p.is_file() for p in paths)


def compiled_graphs() -> int:
    """Graphs Dynamo has compiled in this process plus the AOT packages it built (a sweep that recompiles nothing
    keeps this constant; loading a package counts nothing)."""
    dynamo = sys.modules.get("torch._dynamo.utils")  # never imported by a process that only loads AOT packages
    graphs = int(dynamo.counters["stats"]["unique_graphs"]) if dynamo is not None else 0
    return graphs + _aot_built


def aot_packages(step: Transport, steps_per_call: int, device: torch.device) -> tuple[Path, ...] | None:
    """The two package files of ``step``'s structure in the compile cache (:func:`package_names`), or None where the
    step is compiled by torch.compile instead (a device not in :data:`AOT_DEVICES`, a scripted random-number function, a lat-long
    sampler). Keyed by the structure, ``steps_per_call``, the device type, the torch version, the CPU thread count
    (the kernels are specialised on it), the Inductor options and the package's sources."""
    if device.type not in AOT_DEVICES or step.uniforms is not counter_uniforms or step.sampler is not None:
        return None
    threads = torch.get_num_threads() if device.type == "cpu" else 0
    text = repr((step.structure, steps_per_call, device.type, torch.__version__, threads, TRACK_OPTIONS,
                 VERTEX_OPTIONS, ADVANCE_OPTIONS, package_sources()))
    stem = inductor_cache_dir() / "nrc-aot" / hashlib.sha1(text.encode()).hexdigest()[:20]
    return tuple(stem.with_name(f"{stem.name}-{name}.pt2") for name in package_names(step))


def package_names(step: Transport) -> tuple[str, str]:
    """The step functions a structure is compiled into: ``track`` and ``vertex``, or ``track`` and ``advance``
    where it has the tail's fused step (:attr:`Transport.fusable`): ``advance`` then serves the vertex passes too
    (on slots waiting at a vertex its tracking step changes nothing, so it is the vertex), one package less to
    build."""
    return ("track", "advance") if step.fusable else ("track", "vertex")


class _Package:
    """A step function loaded from an AOTInductor package: ``(F, I, P, density, majorant) -> (F, I)``."""

    def __init__(self, path: Path, device: torch.device) -> None:
        index = -1 if device.type == "cpu" else (device.index if device.index is not None else
                                                 torch.cuda.current_device())
        loader_cls = getattr(getattr(torch._C, "_aoti", None), "AOTIModelPackageLoader", None)
        if loader_cls is not None:  # the C++ loader: imports nothing of Inductor or Dynamo
            self._loader = loader_cls(str(path), "model", False, 1, index)
        else:  # pragma: no cover -- another torch's layout
            from torch._inductor import aoti_load_package

            self._loader = aoti_load_package(str(path))

    def __call__(self, F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
        F, I = self._loader.run([F.contiguous(), I.contiguous(), P, density, majorant])
        return F, I


class _InterruptWatch:
    """A SIGINT inside the block is a stop, whatever torch's code does with it.

    The main thread's handler still runs (it raises ``KeyboardInterrupt``), but code inside torch's tracing can turn
    that exception into another one or swallow it (C-level attribute probes clear any error) and go on building for
    minutes. So after a hit the interrupt is raised again every ``REPEAT_S`` until the block is left, and leaving
    the block after a hit, normally or by any exception, raises ``KeyboardInterrupt``. An interrupt handled while
    the block is being left (inside :meth:`__exit__`, at any depth) only notes the hit: ``__exit__`` raises it, and
    a repeat can never land after the block. After a hit, logging is off until the block is left: torch logs the
    interrupt with its traceback where its dispatch catches it (``fake tensor raised TypeError``), and a stop prints
    one line, not that.
    """

    REPEAT_S = 1.0
    hit = False

    def __enter__(self) -> _InterruptWatch:
        self._prev, self._logging = None, None
        self._left, self._lock = threading.Event(), threading.Lock()
        if threading.current_thread() is threading.main_thread():
            prev = signal.getsignal(signal.SIGINT)
            if callable(prev):  # Python's handler (or the app's): wrap it; SIG_IGN / SIG_DFL stay as they are
                def handler(signum: int, frame: Any) -> None:
                    leaving = self._leaving(frame)
                    if not self.hit and not leaving:
                        self._logging = logging.root.manager.disable
                        logging.disable(logging.CRITICAL)
                        threading.Thread(target=self._repeat, daemon=True).start()
                    self.hit = True
                    if not leaving:
                        prev(signum, frame)

                self._prev = prev
                signal.signal(signal.SIGINT, handler)
        return self

    def _leaving(self, frame: Any) -> bool:
        """The main thread is inside this watch's ``__exit__`` (``frame``: where the handler interrupted it)."""
        while frame is not None:
            if frame.f_code is _InterruptWatch.__exit__.__code__ and frame.f_locals.get("self") is self:
                return True
            frame = frame.f_back
        return False

    def _repeat(self) -> None:
        import _thread

        while not self._left.wait(self.REPEAT_S):
            with self._lock:  # never once the block is left
                if not self._left.is_set():
                    _thread.interrupt_main(signal.SIGINT)

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        with self._lock:
            self._left.set()
        if self._prev is not None:
            signal.signal(signal.SIGINT, self._prev)
        if self._logging is not None:
            logging.disable(self._logging)
        if self.hit and not isinstance(exc, KeyboardInterrupt):
            raise KeyboardInterrupt from exc


def _build_package(fn: Any, args: tuple[Tensor, ...], options: dict[str, Any], path: Path) -> None:
    """Export ``fn`` (slot count and grid / table lengths dynamic, as in :func:`_compile`) and compile it into
    the package ``path`` (written whole, then renamed: a half-written package is never loaded)."""
    from torch._inductor import aoti_compile_and_package
    from torch.export import Dim

    class Step(torch.nn.Module):
        def forward(self, F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> Any:
            return fn(F, I, P, density, majorant)

    n, nd, nm = Dim("slots", min=2), Dim("density", min=2), Dim("majorant", min=2)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.pt2")
    with warnings.catch_warnings():  # torch's own deprecation notices from inside export: not the user's concern
        warnings.simplefilter("ignore", FutureWarning)
        program = torch.export.export(Step(), args, dynamic_shapes=({1: n}, {1: n}, None, {0: nd}, {0: nm}),
                                      strict=False)
        with plain_row_views():  # the state rows as pointers, not per-call tensor views (row_views.py)
            aoti_compile_and_package(program, package_path=str(tmp), inductor_configs=dict(options))
    os.replace(tmp, path)


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
    given slots; ``advance(F, I, inputs)`` (where :attr:`fusable`) one tracking step and the vertices it reaches,
    the driver's tail. A single slot is padded with an idle one (dynamic shapes specialise sizes 0 and 1).
    """

    def __init__(self, step: Transport, steps_per_call: int, compile: bool, device: torch.device,
                 graphs: bool = False) -> None:
        self.step, self.steps_per_call, self.compiled, self.device = step, steps_per_call, compile, device
        # renderer.cuda_graphs: every call through a captured graph of its slot bucket (graphs.py)
        self.graphs = StepGraphs(step.layout.nf, step.layout.ni, device) if graphs else None

        def track(F: Tensor, I: Tensor, P: Tensor, density: Tensor, majorant: Tensor) -> tuple[Tensor, Tensor]:
            for _ in range(steps_per_call):
                F, I = step.track(F, I, P, density, majorant)
            return F, I

        self._track_eager, self._vertex_eager, self._advance_eager = track, step.vertex, step.advance
        # compiled: replaced here (JIT) or by warm_up (AOT)
        self._track, self._vertex, self._advance = track, step.vertex, step.advance
        # the AOT packages of this structure (loaded or built by warm_up), or None: torch.compile
        self.packages = aot_packages(step, steps_per_call, device) if compile else None
        if compile and self.packages is None:
            self._jit()
        self.startup_s: float | None = None if compile else 0.0
        self.cache_hit: bool | None = None

    def _jit(self) -> None:
        """The step functions through torch.compile (lazy: the first calls compile or load them)."""
        inductor_cache_dir()
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
        self._track = _compile(self._track_eager, TRACK_OPTIONS)
        if self.fusable:  # the fused step serves the vertex passes too (package_names)
            self._advance = self._vertex = _compile(self._advance_eager, ADVANCE_OPTIONS)
        else:
            self._vertex = _compile(self._vertex_eager, VERTEX_OPTIONS)

    @property
    def fusable(self) -> bool:
        """The machine has the tail's fused step (:meth:`advance`): the structure traces its shadow rays inline."""
        return self.step.fusable

    def _load_packages(self, track_args: tuple[Tensor, ...], vertex_args: tuple[Tensor, ...]) -> None:
        """The step functions from their AOT packages: loaded, or built first (from the example arguments) when
        absent or unreadable; torch.compile instead when a step cannot be exported."""
        global _aot_built
        loaded = []
        fns = {"track": (self._track_eager, TRACK_OPTIONS, track_args),
               "vertex": (self._vertex_eager, VERTEX_OPTIONS, vertex_args),
               "advance": (self._advance_eager, ADVANCE_OPTIONS, vertex_args)}
        for path, (fn, options, args) in zip(self.packages, (fns[n] for n in package_names(self.step))):
            if path.is_file():
                try:
                    loaded.append(_Package(path, self.device))
                    continue
                except Exception as exc:  # noqa: BLE001 -- a corrupt or foreign file: build it again
                    log.warning("the compiled step %s cannot be loaded (%s); compiling it again", path.name,
                                failure_line(exc) or type(exc).__name__)
            try:
                with _InterruptWatch():  # Ctrl-C inside torch's tracing, however it surfaces: a stop
                    _build_package(fn, args, options, path)
            except Exception as exc:  # noqa: BLE001 -- an op export cannot take: the JIT compiles it
                log.warning("ahead-of-time compile of the step failed (%s: %s); using torch.compile's JIT code "
                            "(slower calls than the packaged step's)", type(exc).__name__, failure_line(exc))
                self.packages = None
                self._jit()
                return
            _aot_built += 1
            loaded.append(_Package(path, self.device))
        self._track, self._vertex = loaded
        if self.fusable:  # the fused step serves the vertex passes too (package_names)
            self._advance = self._vertex

    @staticmethod
    def _call(fn: Any, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        if F.shape[1] >= 2:
            return fn(F, I, inputs.P, inputs.density, inputs.majorant)
        # one slot: padded with an idle one (the compiled functions take sizes from 2; the idle slot's result,
        # whatever it is, is dropped)
        Fo, Io = fn(torch.cat([F, torch.zeros_like(F)], 1), torch.cat([I, torch.zeros_like(I)], 1), inputs.P,
                    inputs.density, inputs.majorant)
        return Fo[:, :1], Io[:, :1]

    @property
    def graph_report(self) -> dict[str, Any] | None:
        """``renderer.cuda_graphs`` as it ran (``None``: off): graphs captured, and why they stopped if they did."""
        if self.graphs is None:
            return None
        return {"captures": self.graphs.captures, "on": self.graphs.on, "reason": self.graphs.reason}

    def _run(self, name: str, fn: Any, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        if self.graphs is not None and self.graphs.on and self.startup_s is not None:  # graphs after the warm-up
            out = self.graphs.run(name, fn, F, I, inputs)
            if out is not None:  # None: the capture failed, graphs are off from here on
                return out
        return self._call(fn, F, I, inputs)

    def track(self, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        return self._run("track", self._track, F, I, inputs)

    def vertex(self, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        return self._run("vertex", self._vertex, F, I, inputs)

    def advance(self, F: Tensor, I: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        """One tracking step and the vertices it reaches (:meth:`Transport.advance`; :attr:`fusable` only)."""
        return self._run("advance", self._advance, F, I, inputs)

    def warm_up(self, inputs: SceneInputs, slots: int) -> float:
        """Compile (or load from the cache) by calls on idle working sets (inductor picks its parallelisation
        from the sizes it sees first); returns the seconds it took (0 when already done)."""
        if self.startup_s is not None:
            return 0.0
        self.cache_hit = (_marker(self.step, self.device).exists() if self.packages is None
                          else packages_cached(self.step, self.steps_per_call, self.device))
        where = inductor_cache_dir()
        if self.cache_hit:
            log.info("loading the compiled transport step from %s (%s)", where,
                     "a few seconds" if self.packages is None else "under a second")
        else:
            log.info("compiling the transport step for this light / estimator structure on %s: once, about 1-3 "
                     "minutes on 2 CPU cores; it is kept in %s, so later runs of any scene of this structure load "
                     "it in %s (renderer.backend=eager skips the compile)", self.device.type, where,
                     "seconds" if self.packages is None else "milliseconds")
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
            k = max(F.shape[1] // 16, 2)
            Fv, Iv = F[:, :k].contiguous(), I[:, :k].contiguous()
            if self.packages is not None:
                scene = (inputs.P, inputs.density, inputs.majorant)
                self._load_packages((F, I, *scene), (Fv, Iv, *scene))
            with _InterruptWatch():  # torch.compile's first calls (the JIT path) trace as well
                self.track(F, I, inputs)
                self.vertex(Fv, Iv, inputs)
                if self.fusable:
                    self.advance(Fv, Iv, inputs)
        finally:
            done.set()
        self.startup_s = time.perf_counter() - t0
        if self.packages is None:  # torch.compile's kernels (the packages are their own record)
            _marker(self.step, self.device).touch()
        if not self.cache_hit:
            log.info("compiled the transport step in %.0f s (cached for the next run)", self.startup_s)
        return self.startup_s


MACHINE_CACHE = 16  # machines kept per process
_machines: list[tuple[tuple[Any, ...], Machine]] = []


def machine_for(step: Transport, steps_per_call: int, compile: bool, device: torch.device,
                graphs: bool = False) -> Machine:
    """The process's machine for ``step``'s structure (built on first use): every tracer of the same structure
    shares it, whatever its scene numbers, grid, camera, spp or seed (``graphs``: through CUDA graphs)."""
    key = (step.key, steps_per_call, compile, str(device), graphs)
    for i, (k, machine) in enumerate(_machines):
        if k == key:
            _machines.append(_machines.pop(i))
            return machine
    machine = Machine(step, steps_per_call, compile, device, graphs)
    _machines.append((key, machine))
    del _machines[:-MACHINE_CACHE]
    return machine


def compiled_machine_ready(step: Transport, steps_per_call: int, device: torch.device) -> bool:
    """This process already holds a warm compiled machine of ``step``'s structure (with or without graphs)."""
    key = (step.key, steps_per_call, True, str(device))
    return any(k[:4] == key and m.startup_s is not None for k, m in _machines)
