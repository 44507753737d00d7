"""Signals during the NRC frame loop: SIGINT / SIGTERM finish the current frame, then the run writes its checkpoint
and outputs (:class:`StopOnSignal`)."""

from __future__ import annotations

import logging
import signal
import threading
from typing import Any

logger = logging.getLogger("nrc")


class StopOnSignal:
    """SIGINT / SIGTERM ask the frame loop to stop after the current frame (``signal`` is set); a second one, or
    one before the first frame is done (a compile, say: nothing to save yet), restores the previous handlers and
    re-raises, stopping at once. Inert outside the main thread, and with ``active=False`` (the frame loop of
    ``nrc.frames``, which the consumer stops by leaving its loop)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, active: bool = True) -> None:
        self.active = active
        self.signal: int | None = None
        self.frame_done = False  # set by the loop after its first frame: before it there is nothing to save
        self._old: dict[int, Any] = {}

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signal is not None or not self.frame_done:  # a second signal, or nothing to save (e.g. compiling)
            self._restore()
            signal.raise_signal(signum)
            return
        self.signal = signum
        logger.warning("%s: finishing the current frame, then writing the checkpoint and the outputs (again to "
                    "stop at once)", signal.Signals(signum).name)

    def _restore(self) -> None:
        for s, old in self._old.items():
            signal.signal(s, old)
        self._old = {}

    def __enter__(self) -> StopOnSignal:
        if self.active and threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._old[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        self._restore()
