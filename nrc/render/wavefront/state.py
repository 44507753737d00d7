"""The named per-slot state of the wavefront (one path and its pending shadow ray per slot).

Every field is a row of one of two packed tensors, float32 ``F (NF, S)`` and int64 ``I (NI, S)``, one
contiguous row per scalar so that the compiled step vectorises over slots. Code never indexes rows by
number: :class:`Layout` unpacks the tensors into a :class:`PathState` of named ``(S,)`` tensors (3-vectors
as tuples of three) and packs it back, and the driver reads rows by name (:meth:`Layout.f`, :meth:`Layout.i`).

Fields (units: world units, radiance in linear RGB):

============ ===== =====================================================================================
``o``        3     ray origin; at a vertex (``flight == VERTEX``) or a cache query, the vertex position
``d``        3     unit propagation direction of the free flight
``t, tmax``  1, 1  current distance along the free flight and its end (box exit)
``beta``     3     throughput (for training paths relative to the last recorded vertex)
``pdf``      1     phase pdf of ``d`` (0: a camera ray; MIS of environment escapes)
``os``       3     shadow ray origin (the vertex that started it; the free flight goes on meanwhile)
``wi``       3     shadow ray direction
``ts, tse``  1, 1  shadow ray distance and end
``tr``       1     shadow ray's running transmittance (ratio tracking)
``csh``      3     shadow ray's contribution weight (light x phase x MIS x throughput), times ``tr`` at the end
``L``        3R    radiance gathered per accumulator row (``R``: the vertex program's ``rows``, 1 for ``pt``)
============ ===== =====================================================================================

Integer fields: ``dest`` (accumulator row of row 0: the pixel, or a training path's discard row), ``key``
and ``cnt`` (counter-based RNG), ``n`` (real scattering events), ``flight`` (one of ``DONE``, ``FLIGHT``,
``VERTEX``, ``QUERY``, ``ESCAPED``), ``shadow`` (0 none, 1 pending in the slot, 2 queued for an external
estimator), ``occupied`` (holds an unharvested path), ``n_shadow_steps`` and ``n_shadow`` (shadow-ray steps
and shadow rays traced in the slot: the work counters, read at harvest); and ``skip_env`` (1: the current
segment's escape does not count the environment, :attr:`Decision.skip_env
<nrc.render.wavefront.program.Decision.skip_env>`) where the vertex program can set it
(:attr:`VertexProgram.skips_env <nrc.render.wavefront.program.VertexProgram.skips_env>`; ``pt`` without reuse
has no such field); and ``srow`` (the ``L`` row the pending shadow ray adds to, set at its vertex) where the program
has several rows.

A renderer's vertex program (:mod:`nrc.render.wavefront.program`) adds its own fields after these (``nrc``: the
termination rule's path spread, the training records' bookkeeping; :mod:`nrc.render.radiance_caching.vertex`).

Memory: ``4 NF + 8 NI`` bytes a slot (156 for ``pt``; 8 more with ``skip_env``; ``nrc`` adds its own fields).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

# flight states
DONE, FLIGHT, VERTEX, QUERY, ESCAPED = 0, 1, 2, 3, 4

_FLOAT = [("o", 3), ("d", 3), ("t", 1), ("tmax", 1), ("beta", 3), ("pdf", 1), ("os", 3), ("wi", 3), ("ts", 1),
          ("tse", 1), ("tr", 1), ("csh", 3)]
_INT = ["dest", "key", "cnt", "n", "flight", "shadow", "occupied", "n_shadow_steps", "n_shadow"]


def where3(m: Tensor, a: tuple, b: tuple) -> tuple:
    """Component-wise ``torch.where(m, a, b)`` of 3-vectors in component form (the state's vectors)."""
    return tuple(torch.where(m, x, y) for x, y in zip(a, b))


@dataclass
class PathState:
    """The unpacked state: every attribute an ``(S,)`` tensor, a 3-tuple of them, or (``L``) a tuple of
    ``R`` 3-tuples, and the vertex program's fields. See the module docstring for the meanings."""

    o: Any = None
    d: Any = None
    t: Any = None
    tmax: Any = None
    beta: Any = None
    pdf: Any = None
    os: Any = None
    wi: Any = None
    ts: Any = None
    tse: Any = None
    tr: Any = None
    csh: Any = None
    L: Any = None
    dest: Any = None
    key: Any = None
    cnt: Any = None
    n: Any = None
    flight: Any = None
    shadow: Any = None
    occupied: Any = None
    n_shadow_steps: Any = None
    n_shadow: Any = None
    skip_env: Any = None
    srow: Any = None
    # a vertex program's own fields are set as further attributes by Layout.unpack


@dataclass(frozen=True)
class Layout:
    """Row layout of the packed state for ``rows`` accumulator rows and a vertex program's extra fields
    (``extra_float``: ``(name, width)`` pairs; ``extra_int``: names)."""

    rows: int = 1
    extra_float: tuple[tuple[str, int], ...] = ()
    extra_int: tuple[str, ...] = ()
    skip_env: bool = False
    _f: dict = field(default_factory=dict, compare=False, repr=False)
    _i: dict = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def of(cls, program: Any) -> Layout:
        """The layout of a vertex program (:mod:`nrc.render.wavefront.program`)."""
        return cls(program.rows, tuple(program.float_fields), tuple(program.int_fields), program.skips_env)

    def __post_init__(self) -> None:
        pos = 0
        for name, width in _FLOAT + [("L", 3 * self.rows)] + list(self.extra_float):
            self._f[name] = (pos, width)
            pos += width
        object.__setattr__(self, "nf", pos)
        for k, name in enumerate(_INT + ["skip_env"] * self.skip_env + ["srow"] * (self.rows > 1)
                                 + list(self.extra_int)):
            self._i[name] = k
        object.__setattr__(self, "ni", len(self._i))

    def f(self, name: str) -> slice | int:
        """Row index (scalar field) or row slice (vector field) of float field ``name`` in ``F``."""
        pos, width = self._f[name]
        return pos if width == 1 else slice(pos, pos + width)

    def i(self, name: str) -> int:
        """Row of integer field ``name`` in ``I``."""
        return self._i[name]

    def zeros(self, n: int, device: torch.device | str) -> tuple[Tensor, Tensor]:
        """Packed state of ``n`` idle slots."""
        return torch.zeros(self.nf, n, device=device), torch.zeros(self.ni, n, dtype=torch.long, device=device)

    def unpack(self, F: Tensor, I: Tensor) -> PathState:
        s = PathState()
        rows = F.unbind(0)
        for name, (pos, width) in self._f.items():
            if name == "L":
                val: Any = tuple(tuple(rows[pos + 3 * j:pos + 3 * j + 3]) for j in range(self.rows))
            else:
                val = rows[pos] if width == 1 else tuple(rows[pos:pos + width])
            setattr(s, name, val)
        irows = I.unbind(0)
        for name, k in self._i.items():
            setattr(s, name, irows[k])
        return s

    def pack(self, s: PathState) -> tuple[Tensor, Tensor]:
        out: list[Tensor] = []
        for name, (_, width) in self._f.items():
            val = getattr(s, name)
            if name == "L":
                for row in val:
                    out.extend(row)
            elif width == 1:
                out.append(val)
            else:
                out.extend(val)
        return torch.stack(out), torch.stack([getattr(s, name) for name in self._i])
