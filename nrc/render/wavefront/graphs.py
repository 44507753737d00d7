"""CUDA graphs of the step (``renderer.cuda_graphs``): a call's slots padded up to a power-of-two bucket, one graph
captured per step function and bucket, replayed.

On a GPU a step call costs its launches, not its slots, until the working set is large: the compiled step's kernels
and the Python around them (Dynamo's guards, Inductor's wrapper; the eager step launches hundreds of kernels), tens
of microseconds a call whatever the slot count, and a frame makes hundreds of calls (``pt``'s 1-spp frame of a
thick cloud ~2,400). A graph replays the captured kernels with one launch. A graph has fixed shapes, so a call of
``S`` slots runs in the graph of bucket ``B = max(MIN_BUCKET, 2^ceil(log2 S))``: its inputs are copied into the
bucket's static buffers, the slots past ``S`` are idle (zeros: :meth:`Layout.zeros`, which every step leaves as
they are, and whose results are dropped), and the first ``S`` columns of the static outputs are copied out (the
driver keeps and edits its state in place; the next replay overwrites the graph's own buffers). Each slot's
result depends on its own column only, so a padded call gives what the unpadded one gives.

The scene inputs: ``P`` (the scene's numbers, which change from frame to frame under animation or
``renderer.debias``) is copied into a static buffer every call; the density grid and the majorant table are
captured by address, so a call with other tensors (another scene on the same machine) captures the bucket again.

Capture: warm-up calls on a side stream (the first compiles, Inductor and Dynamo settle), then the capture into a
pool shared by the machine's graphs (they never run concurrently). A capture that fails (an op that
synchronises, say) turns graphs off for the machine and says why (:attr:`StepGraphs.reason`); the machine then
runs its calls as without them. Memory: per captured bucket, the static inputs and outputs (``2 x (n_float + n_int rows) x B``
elements, 4 / 8 bytes) and what the step allocates inside the graph's pool.

``capture`` is a parameter so that the bookkeeping (buckets, padding, static buffers, recapture) runs without a
GPU: :func:`call_capture` replays by calling the function again on the static inputs and copying into the static
outputs, which is what a replayed graph does (``tests/test_pt_compiled.py``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from nrc.errors import failure_line

log = logging.getLogger(__name__)

MIN_BUCKET = 64  # the smallest graph (the driver compacts no lower than MIN_SLOTS = 64 either)
WARMUP_CALLS = 2  # calls on a side stream before a capture (the first may compile)

Step = Callable[..., tuple[Tensor, Tensor]]
# (fn, static arguments, pool) -> (replay, static outputs)
Capture = Callable[[Step, tuple[Tensor, ...], Any], tuple[Callable[[], None], tuple[Tensor, Tensor]]]


def bucket(n: int) -> int:
    """The slot count of the graph that runs a call of ``n`` slots."""
    return max(MIN_BUCKET, 1 << (max(n, 1) - 1).bit_length())


def cuda_capture(fn: Step, args: tuple[Tensor, ...], pool: Any) -> tuple[Callable[[], None], tuple[Tensor, Tensor]]:
    """Capture ``fn(*args)`` into a CUDA graph (after :data:`WARMUP_CALLS` calls on a side stream)."""
    device = args[0].device
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        for _ in range(WARMUP_CALLS):
            fn(*args)
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, pool=pool):
        out = fn(*args)
    return graph.replay, out


def call_capture(fn: Step, args: tuple[Tensor, ...], pool: Any) -> tuple[Callable[[], None], tuple[Tensor, Tensor]]:
    """What a replayed graph does, without a GPU: each replay calls ``fn`` on the static inputs and writes the
    result into the static outputs of the first call."""
    out = fn(*args)

    def replay() -> None:
        for static, new in zip(out, fn(*args)):
            static.copy_(new)

    return replay, out


@dataclass
class _Graph:
    replay: Callable[[], None]
    F: Tensor  # static inputs (n_float, B), (n_int, B)
    I: Tensor
    P: Tensor
    out: tuple[Tensor, Tensor]  # static outputs
    scene: tuple  # the density grid's and the majorant table's address and size at capture
    keep: tuple  # those tensors, kept alive while the graph reads them
    filled: int = 0  # columns holding the last call's slots (the rest idle)


class StepGraphs:
    """The graphs of one machine: ``run(name, fn, F, I, inputs)`` is ``fn(F, I, P, density, majorant)`` for the
    state ``F`` ``(n_float, S)``, ``I`` ``(n_int, S)`` through bucket ``bucket(S)``'s graph of ``name``, or
    ``None`` when that graph's capture failed (graphs are then off: the caller runs the step itself).

    Attributes:
        captures: graphs captured so far (a bucket captured again for another scene counts again).
        reason: why graphs were turned off (a capture failed), else ``None``.
    """

    def __init__(self, n_float: int, n_int: int, device: torch.device, capture: Capture | None = None) -> None:
        self.n_float, self.n_int, self.device = n_float, n_int, device
        self._capture = capture if capture is not None else cuda_capture
        self._pool = torch.cuda.graph_pool_handle() if capture is None else None
        self._graphs: dict[tuple[str, int], _Graph] = {}
        self.captures = 0
        self.reason: str | None = None

    @property
    def on(self) -> bool:
        return self.reason is None

    def run(self, name: str, fn: Step, F: Tensor, I: Tensor, inputs: Any) -> tuple[Tensor, Tensor] | None:
        S = F.shape[1]
        B = bucket(S)
        scene = (inputs.density.data_ptr(), inputs.density.numel(), inputs.majorant.data_ptr(),
                 inputs.majorant.numel(), inputs.P.numel())
        g = self._graphs.get((name, B))
        if g is None or g.scene != scene:
            self._graphs.pop((name, B), None)
            g = self._new(fn, B, inputs, scene)
            if g is None:  # the capture failed: no graphs from here on, the caller runs the step itself
                return None
            self._graphs[(name, B)] = g
        g.F[:, :S].copy_(F)
        g.I[:, :S].copy_(I)
        if g.filled > S:  # the columns of a larger earlier call: idle again
            g.F[:, S:g.filled].zero_()
            g.I[:, S:g.filled].zero_()
        g.filled = S
        g.P.copy_(inputs.P)
        g.replay()
        return g.out[0][:, :S].clone(), g.out[1][:, :S].clone()

    def _new(self, fn: Step, B: int, inputs: Any, scene: tuple) -> _Graph | None:
        F = torch.zeros(self.n_float, B, device=self.device)
        I = torch.zeros(self.n_int, B, dtype=torch.long, device=self.device)
        P = inputs.P.clone()
        try:
            replay, out = self._capture(fn, (F, I, P, inputs.density, inputs.majorant), self._pool)
        except Exception as exc:  # noqa: BLE001 -- an op that cannot be captured: run without graphs
            self.reason = f"capture of a {B}-slot step failed: {type(exc).__name__}: {failure_line(exc)}"
            self._graphs.clear()
            log.warning("renderer.cuda_graphs: %s; running the step without graphs", self.reason)
            return None
        self.captures += 1
        return _Graph(replay, F, I, P, out, scene, (inputs.density, inputs.majorant))
