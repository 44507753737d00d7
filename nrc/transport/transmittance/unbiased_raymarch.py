"""Unbiased ray-marching transmittance (Kettunen, d'Eon, Pantaleoni, Novák 2021), as in ALGORITHMS.md.

Per ray, on its segment ``[a, b]`` inside the box (length ``L``):

1. **Comb**: one uniform offset ``u``, step ``h = L / M``, ``X = h * sum_{j<M} sigma_t(a + (u + j) h)``:
   unbiased for ``tau``, exact for constant ``sigma_t``.
2. **Tuple size** from a conservative control optical thickness ``tau_c = tau_major - tau_minor`` (brick
   majorant minus minorant integrated along the segment, :func:`nrc.transport.tracking.optical_depth_bounds`,
   the sum over :func:`nrc.transport.tracking.majorant_segments`): ``N_cmf = ceil(cbrt((0.015+tau_c)(0.65+tau_c)(60.3+tau_c)))``,
   ``M = max(1, floor(N_cmf / 1.31945 + 0.5))`` (capped at ``max_m``).
3. **Order** ``N`` by the aggressive Bhanot–Kennedy roulette (``p_z = 0.9``, ``K = 2``, ``c = 2``), truncated at
   ``max_order``: ``P(N >= k) = 1, 0.1, 0.1, 0.0667, 0.0333, 0.0133, ...`` (:func:`roulette_probabilities`).
4. ``N + 1`` independent combs ``X_0..X_N``; for each pivot ``i``, the elementary symmetric means ``m_k`` of
   ``d_j = X_i - X_j`` (``j != i``) give ``exp(-X_i) * sum_k m_k / (k! P(N >= k))`` (divided by ``P``, not
   multiplied); the estimate is the mean over the ``N + 1`` pivots (a U-statistic).
5. Not bounded to ``[0, 1]`` and never clamped.

Shortcuts that change no float32 result: rays whose ``tau_major`` is 0 return exactly 1 (the density is 0 on
the whole segment) and rays whose ``tau_minor`` exceeds 110 return 0 (``T <= exp(-110) < 1e-47``, below the
smallest float32 denormal), both without lookups.

Batching: rays have different ``M`` and ``N``. All ``sum_r (N_r + 1) M_r`` lookups of a chunk are laid out flat
(ray-major, then comb, then sample), evaluated in one ``sigma_t`` call and summed per (ray, comb) with
``index_add_``; chunks hold at most ``chunk_lookups`` lookups (a single ray larger than that is its own chunk).
The symmetric means run in float64 on the few rays with ``N >= 1`` only, vectorised over pivots and orders
(a loop of at most ``max_order + 1`` steps).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from nrc.transport.tracking import TrackingStats, clip_segments, optical_depth_bounds

OPAQUE_TAU = 110.0


def roulette_probabilities(max_order: int = 10, p_z: float = 0.9, k: int = 2, c: float = 2.0) -> Tensor:
    """``P(N >= j)`` for ``j = 0..max_order`` of the aggressive Bhanot–Kennedy roulette (float64 ``(max_order+1,)``).

    ``N = 0`` with probability ``p_z``; otherwise ``N >= k`` and each further order ``j > k`` is reached with
    probability ``min(1, c / j)``. The defaults give ``1, 0.1, 0.1, 0.0667, 0.0333, 0.0133, ...``.
    """
    probs = [1.0]
    for j in range(1, max_order + 1):
        probs.append(1.0 - p_z if j <= k else probs[-1] * min(1.0, c / j))
    return torch.tensor(probs, dtype=torch.float64)


def sample_order(u: Tensor, probs: Tensor) -> Tensor:
    """Orders ``N`` ``(R,)`` (long) from uniforms ``u`` ``(R,)``: ``N = #{j >= 1 : u < P(N >= j)}`` (inverse CDF),
    so ``P(N >= j)`` holds exactly for ``j <= max_order`` and ``N <= max_order``."""
    return (u.to(torch.float64)[:, None] < probs[None, 1:].to(u.device)).sum(dim=1)


def tuple_size(tau_c: Tensor, max_m: int) -> Tensor:
    """Comb size ``M`` ``(R,)`` (long) from the control optical thickness (Kettunen et al. 2021), capped at ``max_m``."""
    tc = tau_c.to(torch.float64).clamp(min=0.0)
    n_cmf = torch.ceil(torch.pow((0.015 + tc) * (0.65 + tc) * (60.3 + tc), 1.0 / 3.0))
    m = torch.floor(n_cmf / 1.31945 + 0.5).clamp(min=1.0, max=float(max_m))
    return m.long()


def combs(
    grid,
    origin: Tensor,
    direction: Tensor,
    a: Tensor,
    b: Tensor,
    m: Tensor,
    n_combs: Tensor,
    gen: torch.Generator,
    chunk_lookups: int = 1 << 20,
) -> Tensor:
    """Independent comb estimates of the optical depth of ``[a, b]``.

    Args:
        m: ``(R,)`` comb sizes (>= 1); n_combs: ``(R,)`` combs per ray (>= 1).

    Returns:
        ``X`` ``(R, P)`` float32 with ``P = max(n_combs)``: ``X[r, c] = h_r sum_j sigma_t(a_r + (u_rc + j) h_r)``
        for ``c < n_combs[r]`` (0 beyond).
    """
    r_all = origin.shape[0]
    dev = origin.device
    p = int(n_combs.max()) if r_all else 1
    X = torch.zeros(r_all, p, dtype=torch.float32, device=dev)
    if r_all == 0:
        return X
    offsets = torch.rand((r_all, p), generator=gen, device=dev)
    h = (b - a) / m.to(torch.float32)
    start = origin + a[:, None] * direction
    step = h[:, None] * direction
    counts = m * n_combs
    excl = torch.cumsum(counts, 0) - counts
    ids = torch.div(excl, chunk_lookups, rounding_mode="floor")
    _, sizes = torch.unique_consecutive(ids, return_counts=True)
    s = 0
    for size in sizes.tolist():
        e = s + size
        cnt = counts[s:e]
        total = int(cnt.sum())
        ray = torch.repeat_interleave(torch.arange(e - s, device=dev), cnt, output_size=total)
        local = torch.arange(total, device=dev) - (excl[s:e] - excl[s])[ray]
        mr = m[s:e][ray]
        comb = torch.div(local, mr, rounding_mode="floor")
        j = (local - comb * mr).to(torch.float32)
        slot = ray * p + comb
        pos = offsets[s:e].reshape(-1)[slot] + j
        x = start[s:e][ray] + pos[:, None] * step[s:e][ray]
        sigma = grid.sigma_t(x)
        X[s:e].view(-1).index_add_(0, slot, sigma)
        s = e
    return X * h[:, None]


def symmetric_mean_estimate(X: Tensor, order: Tensor, probs: Tensor) -> Tensor:
    """The U-statistic of step 4 for rays with ``N >= 1``.

    Args:
        X: ``(S, P)`` combs (columns ``> order`` ignored); order: ``(S,)`` ``N``; probs: ``P(N >= k)``.

    Returns:
        ``(S,)`` float64 estimates ``mean_i exp(-X_i) sum_k m_k(X_i - X_j, j != i) / (k! P(N >= k))``.
    """
    Xd = X.to(torch.float64)
    s_rays, p = Xd.shape
    dev = X.device
    ar = torch.arange(p, device=dev)
    diff = Xd[:, :, None] - Xd[:, None, :]  # [ray, pivot i, value j] = X_i - X_j
    pivot_ok = ar[None, :] <= order[:, None]  # (S, P)
    m = torch.zeros(s_rays, p, p, dtype=torch.float64, device=dev)  # [ray, pivot, k]
    m[..., 0] = 1.0
    n = torch.zeros(s_rays, p, dtype=torch.float64, device=dev)
    kk = torch.arange(1, p, device=dev, dtype=torch.float64)
    for j in range(p):
        valid = (j <= order)[:, None] & (ar != j)[None, :]  # (S, P)
        n = n + valid
        x = diff[:, :, j, None]
        upd = m[..., 1:] + (kk / n.clamp(min=1.0)[..., None]) * (m[..., :-1] * x - m[..., 1:])
        m[..., 1:] = torch.where(valid[..., None], upd, m[..., 1:])
    fact = torch.tensor([math.factorial(k) for k in range(p)], dtype=torch.float64, device=dev)
    coef = 1.0 / (fact * probs[:p].to(dev))
    est = torch.exp(-Xd) * (m * coef).sum(dim=-1)
    est = torch.where(pivot_ok, est, torch.zeros_like(est))
    return est.sum(dim=1) / (order.to(torch.float64) + 1.0)


def estimate(
    grid,
    majorants,
    origin: Tensor,
    direction: Tensor,
    t0: float | Tensor | None,
    t1: float | Tensor | None,
    gen: torch.Generator,
    *,
    max_order: int = 10,
    max_m: int = 1024,
    p_z: float = 0.9,
    k: int = 2,
    c: float = 2.0,
    tau_c_scale: float = 1.0,
    chunk_lookups: int = 1 << 20,
    return_stats: bool = False,
) -> Tensor | tuple[Tensor, TrackingStats]:
    """Unbiased ray-marching transmittance of the segments ``[t0, t1]`` (clipped to the box).

    Args:
        max_order: truncation of the order roulette (terms above it are dropped: a negligible bias).
        max_m: cap on the comb size (only reached for ``tau_c > ~1150``; the estimate stays unbiased up to the
            truncation, but its variance grows).
        p_z, k, c: the Bhanot–Kennedy roulette.
        tau_c_scale: multiplier on the control optical thickness before the tuple-size formula (1 = as
            specified; larger values buy lower variance with more lookups, see docs/transmittance.md).
        chunk_lookups: lookups evaluated per ``sigma_t`` call.
        return_stats: also return :class:`~nrc.transport.tracking.TrackingStats` (``lookups = collisions =
            sum (N+1) M``).

    Returns:
        ``T`` ``(N,)`` float32, unbiased up to the truncation, not bounded to ``[0, 1]``.
    """
    direction = direction.to(torch.float32)
    o, a, b = clip_segments(grid, origin, direction, t0, t1)
    n_rays = o.shape[0]
    T = torch.ones_like(a)
    st = TrackingStats()
    todo = torch.nonzero(b > a).squeeze(1)
    st.rays = int(todo.numel())
    if st.rays and majorants.global_majorant > 0:
        o, d, a, b = o[todo], direction[todo], a[todo], b[todo]
        tau_major, tau_minor = optical_depth_bounds(majorants, o, d, a, b)
        probs = roulette_probabilities(max_order, p_z, k, c)
        order = sample_order(torch.rand(todo.numel(), generator=gen, device=o.device), probs)
        m = tuple_size(float(tau_c_scale) * (tau_major - tau_minor), max_m)
        opaque = tau_minor > OPAQUE_TAU
        march = (tau_major > 0) & ~opaque
        Tt = torch.where(opaque, torch.zeros_like(a), torch.ones_like(a))
        sel = torch.nonzero(march).squeeze(1)
        if sel.numel():
            om = order[sel]
            X = combs(grid, o[sel], d[sel], a[sel], b[sel], m[sel], om + 1, gen, chunk_lookups)
            Ts = torch.exp(-X[:, 0])
            hi = torch.nonzero(om > 0).squeeze(1)
            if hi.numel():
                Ts[hi] = symmetric_mean_estimate(X[hi], om[hi], probs).to(torch.float32)
            Tt[sel] = Ts
            st.lookups = st.collisions = int((m[sel] * (om + 1)).sum())
            st.iterations = 1
        T[todo] = Tt
    assert T.shape[0] == n_rays
    return (T, st) if return_stats else T
