"""The one description of the machine a measurement ran on (results record it; equal-time results of different
machines are never merged: :func:`lab.jobs.check_one_machine_type` compares these strings)."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine(device: str | None = None) -> str:
    """What a time measurement depends on: the CPU model, its core count, torch's intra-op threads and version,
    and the GPU when ``device`` is a CUDA device (a node's name is not part of it: nodes of one type are one
    machine type)."""
    import torch

    gpu = ""
    if device is not None and str(device).startswith("cuda") and torch.cuda.is_available():
        gpu = f", GPU {torch.cuda.get_device_name(torch.device(device))}"
    return (f"{cpu_model()}, {os.cpu_count() or 0} cores, {torch.get_num_threads()} threads, "
            f"torch {torch.__version__}{gpu}")
