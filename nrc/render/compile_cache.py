"""Where the compiled transport steps are kept, and what makes them stale: torch-free, so that a sweep's launching
process can check a job's packages without importing torch (``nrc.app.SweepSetup``).

The cache is ``$TORCHINDUCTOR_CACHE_DIR``, set to ``~/.cache/nrc/inductor`` (``$XDG_CACHE_HOME/nrc/inductor``)
when unset; the AOT packages are under its ``nrc-aot/`` (:mod:`nrc.render.wavefront.machine`). A package is keyed,
among other things, by a hash of :data:`STEP_SOURCES`: an edit to any of those files makes new packages.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

from nrc.io.disk_cache import source_hash

# The packages and files whose code the traced step runs (tests/test_pt_compiled.py checks that the step's imports
# stay in them), the renderers' vertex programs among them (nrc.render.wavefront.program): an edit to any of these
# files makes new AOT packages; a stale package would run the old code unnoticed.
STEP_SOURCES = ("render/wavefront", "render/radiance_caching/vertex.py", "render/reuse/hook.py", "transport",
                "volume")


def default_inductor_cache() -> str:
    return str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nrc" / "inductor")


def inductor_cache_dir() -> Path:
    """The persistent compile cache: ``$TORCHINDUCTOR_CACHE_DIR``, set to ``~/.cache/nrc/inductor`` when unset."""
    path = Path(os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", default_inductor_cache()))
    path.mkdir(parents=True, exist_ok=True)
    return path


@functools.lru_cache(maxsize=1)
def package_sources() -> str:
    """A hash of the :data:`STEP_SOURCES` files."""
    root = Path(__file__).resolve().parents[1]
    return source_hash([f for d in STEP_SOURCES
                        for f in ([root / d] if d.endswith(".py") else sorted((root / d).rglob("*.py")))])
