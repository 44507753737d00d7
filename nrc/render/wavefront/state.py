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
``wi``       3     shadow ray direction
``ts, tse``  1, 1  shadow ray distance and end
``tr``       1     shadow ray's running transmittance (ratio tracking)
``csh``      3     shadow ray's contribution weight (light x phase x MIS x throughput), times ``tr`` at the end
``L``        3R    radiance gathered per accumulator row (``R = 1`` for ``pt``, ``V + 1`` for ``nrc``)
``spread``   1     (nrc) path spread of the ``spread`` termination rule
``a0``       1     (nrc) spread at the first vertex
``x_prev``   3     (nrc) previous vertex (the camera at first)
============ ===== =====================================================================================

Integer fields: ``dest`` (accumulator row of row 0: the pixel, or a training path's discard row), ``key``
and ``cnt`` (counter-based RNG), ``n`` (real scattering events), ``flight`` (one of ``DONE``, ``FLIGHT``,
``VERTEX``, ``QUERY``, ``ESCAPED``), ``shadow`` (0 none, 1 pending in the slot, 2 queued for an external
estimator), ``occupied`` (holds an unharvested path), ``n_shadow_steps``; for ``nrc`` also ``pid`` (path
id), ``rec_base`` (first training record of a training path, -1 for render paths), ``n_term`` (vertex at
which the path terminates into the cache, 0 undecided), ``extra`` (vertices past the render stop),
``never`` (never terminates: 1 a training path's unbiased suffix, :data:`CONTINUED` a render path that would have
terminated into the cache and goes on as a path-traced suffix, ``renderer.debias``), ``rec`` (training record
written at the last vertex, -1 none).

Memory: ``4 NF + 8 NI`` bytes a slot (136 for ``pt``, 268 for ``nrc`` with ``V = 4``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

# flight states
DONE, FLIGHT, VERTEX, QUERY, ESCAPED = 0, 1, 2, 3, 4
# ``never`` of a render path continued past its cache termination (renderer.debias): its contributions from there
# on go to accumulator row 1, the suffix row (the driver maps it to the sample's own row of the accumulator)
CONTINUED = 2

_FLOAT = [("o", 3), ("d", 3), ("t", 1), ("tmax", 1), ("beta", 3), ("pdf", 1), ("wi", 3), ("ts", 1), ("tse", 1),
          ("tr", 1), ("csh", 3)]
_FLOAT_NRC = [("spread", 1), ("a0", 1), ("x_prev", 3)]
_INT = ["dest", "key", "cnt", "n", "flight", "shadow", "occupied", "n_shadow_steps"]
_INT_NRC = ["pid", "rec_base", "n_term", "extra", "never", "rec"]


def just_continued(never_before: Tensor, never_after: Tensor) -> Tensor:
    """Slots whose render path the vertex step between the two ``never`` values continued past its cache
    termination (:data:`CONTINUED`, ``renderer.debias``)."""
    return (never_after == CONTINUED) & (never_before != CONTINUED)


def accumulator_row(rec_base: Tensor, n: Tensor, V: int, never: Tensor | None = None) -> Tensor:
    """Accumulator row ``(S,)`` of each slot's current segment: a training path's ``min(n, V)`` (row 0 is its
    discard row before the first vertex); for a render path 0 (its ``dest``), or 1 (its suffix row) once it is
    :data:`CONTINUED` past its cache termination (``never`` given: ``renderer.debias``)."""
    render = torch.zeros_like(n) if never is None else (never == CONTINUED).long()
    return torch.where(rec_base >= 0, n.clamp(max=V), render)


@dataclass
class PathState:
    """The unpacked state: every attribute an ``(S,)`` tensor, a 3-tuple of them, or (``L``) a tuple of
    ``R`` 3-tuples; ``nrc`` fields are ``None`` for ``pt``. See the module docstring for the meanings."""

    o: Any = None
    d: Any = None
    t: Any = None
    tmax: Any = None
    beta: Any = None
    pdf: Any = None
    wi: Any = None
    ts: Any = None
    tse: Any = None
    tr: Any = None
    csh: Any = None
    L: Any = None
    spread: Any = None
    a0: Any = None
    x_prev: Any = None
    dest: Any = None
    key: Any = None
    cnt: Any = None
    n: Any = None
    flight: Any = None
    shadow: Any = None
    occupied: Any = None
    n_shadow_steps: Any = None
    pid: Any = None
    rec_base: Any = None
    n_term: Any = None
    extra: Any = None
    never: Any = None
    rec: Any = None


@dataclass(frozen=True)
class Layout:
    """Row layout of the packed state for ``rows`` accumulator rows (``nrc``: with the NRC fields)."""

    rows: int = 1
    nrc: bool = False
    _f: dict = field(default_factory=dict, compare=False, repr=False)
    _i: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        pos = 0
        for name, width in _FLOAT + [("L", 3 * self.rows)] + (_FLOAT_NRC if self.nrc else []):
            self._f[name] = (pos, width)
            pos += width
        object.__setattr__(self, "nf", pos)
        for k, name in enumerate(_INT + (_INT_NRC if self.nrc else [])):
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
