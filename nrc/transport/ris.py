"""Resampled importance sampling of lights (``renderer.light_selection=ris``; Talbot et al. 2005, the light sampling
of Q2VKPT), and the one resampling choice (:func:`ris_choice`), also the reservoirs' in ``nrc.render.reuse``.

``M`` candidates ``x_i`` are drawn from the source distribution ``p_src`` (the ``power`` choice times the chosen
light's own sampling pdf, :meth:`~nrc.transport.light_sampling.LightTable.sample`), weighted
``w_i = p_hat(x_i) / p_src(x_i)`` with ``p_hat`` the luminance of the unshadowed contribution (emitted radiance x
``1/r^2`` x phase value, no transmittance); one ``y`` is kept with probability ``w_y / sum w`` and its shadow ray
traced, weighted ``f(y) sum w / (M p_hat(y))`` (:func:`resample`). Unbiased for every ``M`` (``M = 1`` is
``power``). MIS against phase sampling of the environment uses ``p_src`` in both weights (the RIS pdf of ``y`` is
not tractable), so the two weights still sum to one for every direction.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from nrc.transport.lights import luminance3



Candidate = tuple  # (wi (3-tuple), distance, weight (3-tuple), light_pdf, is_env), component form


def resample(candidates: list[Candidate], phase_of: Callable[[tuple], Tensor], u: Tensor) -> tuple[Candidate, Tensor]:
    """Resampled importance sampling over next-event candidates (module docstring).

    Each candidate is a sample of the source distribution as
    :meth:`~nrc.transport.light_sampling.LightTable.sample` returns it: its
    ``weight`` is the light's contribution over ``p_src`` (without phase and transmittance), so its RIS weight
    is ``w_i = p_hat / p_src = luminance(weight_i) x phase(wi_i)``. One candidate is kept with probability
    ``w / sum w`` (:func:`ris_choice`, by the uniform ``u``) and its ``weight`` replaced by
    ``weight_y sum w / (M luminance(weight_y) phase(wi_y))``, so that the caller's
    ``weight x phase x transmittance`` is the RIS estimate ``f(y) sum w / (M p_hat(y))``.
    Where every weight is zero the kept weight is zero. ``light_pdf`` stays the source pdf (the MIS weights').

    Returns:
        ``(chosen candidate, sum w)`` (all ``(N,)`` components).
    """
    ws = [luminance3(c[2]) * phase_of(c[0]) for c in candidates]
    sel, total = ris_choice(ws, u)
    chosen, chosen_w = candidates[0], ws[0]
    for i in range(1, len(candidates)):
        take = sel == i
        chosen, chosen_w = _select(take, candidates[i], chosen), torch.where(take, ws[i], chosen_w)
    # weight / (luminance x phase) = weight / chosen_w; times sum w / M
    scale = torch.where(chosen_w > 0, total / (len(candidates) * chosen_w.clamp(min=1e-30)), torch.zeros_like(total))
    wi, dist, weight, pdf, env = chosen
    return (wi, dist, tuple(c * scale for c in weight), pdf, env), total


def ris_choice(ws: list[Tensor], u: Tensor) -> tuple[Tensor, Tensor]:
    """The one resampling choice (RIS here, the reservoirs' resampling and merging in ``nrc.render.reuse``).

    ``ws``: ``m`` weights ``(N,)``, ``u`` ``(N,)`` uniforms. Returns the index ``(N,)`` (int64) kept with
    probability ``w_i / sum w``: the first whose running sum exceeds ``u sum w``, where rounding leaves none the
    last positive weight, 0 where every weight is 0; and ``sum w`` ``(N,)``. Streams over the list (no stacked
    ``(N, m)`` tensor: the compiled step's form)."""
    total = ws[0]
    for w in ws[1:]:
        total = total + w
    target = u * total
    run = torch.zeros_like(total)
    first = torch.zeros_like(total, dtype=torch.int64)
    last = torch.zeros_like(first)
    picked = torch.zeros_like(total, dtype=torch.bool)
    for i, w in enumerate(ws):
        run = run + w
        pos = w > 0
        take = ~picked & pos & (target < run)
        first, last = torch.where(take, i, first), torch.where(pos, i, last)
        picked = picked | take
    return torch.where(picked, first, last), total


def _select(m: Tensor, a: Candidate, b: Candidate) -> Candidate:
    """Candidate-wise ``where(m, a, b)``."""
    def pick(new: tuple, old: tuple) -> tuple:
        return tuple(torch.where(m, n, o) for n, o in zip(new, old))

    return (pick(a[0], b[0]), torch.where(m, a[1], b[1]), pick(a[2], b[2]), torch.where(m, a[3], b[3]),
            torch.where(m, a[4], b[4]))
