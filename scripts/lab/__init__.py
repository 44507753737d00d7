"""The lab: code shared by the measurement scripts of ``scripts/`` (never imported by the package ``nrc``).

A script run as ``python scripts/<tool>.py`` has ``scripts/`` first on ``sys.path``, so ``from lab import ...``
works as it is; tests put ``scripts/`` on the path themselves (``tests/conftest.py``). Each tool's own code lives in
its script; here only what several tools use:

* :mod:`lab.render` -- compose, load the scene, build a renderer (``nrc.render.registry.make_renderer``); timed path
  tracer renders and NRC runs of a loaded scene;
* :mod:`lab.analysis` -- equal-time comparisons: the path tracer's Pareto front, log-log interpolation, equal-time
  ratios and crossovers;
* :mod:`lab.per_frame` -- the per-frame pieces of animated measurements (a frame's reference, scores raw and
  denoised);
* :mod:`lab.jobs` -- measurements as submitit jobs, refusing results of mixed machine types;
* :mod:`lab.machine` -- the one description of the machine a measurement ran on;
* :mod:`lab.points` -- the named points of the optical-depth measurements (the thick preset's density scales and
  albedos, their references);
* :mod:`lab.tables` -- the number format of every generated table, and a result folder's files.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from nrc.errors import NRCError

REPO = Path(__file__).resolve().parents[2]  # the checkout: the lab lives in it (docs/, outputs/, multirun/ there)
SHARED_DATA = REPO.parent / "shared" / "data"  # the Disney cloud and other large inputs, beside the checkout


def repo_relative(path: Path | str) -> str:
    """``path`` relative to the checkout when it lies in it (results and pages name no machine's path), else as is."""
    path = Path(path)
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def exit_status(tool: str, work: Callable[[], object]) -> int:
    """Run ``work``; a user's error (:class:`nrc.errors.NRCError`) becomes one line ``<tool>: error: ...`` on stderr
    and exit status 2, else 0."""
    try:
        work()
    except NRCError as exc:
        print(f"{tool}: error: {exc}", file=sys.stderr)
        return 2
    return 0
