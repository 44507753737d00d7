"""Henyey–Greenstein phase function: density and importance sampling (float32, batched).

Convention: ``mu`` is the cosine of the angle between the incoming and the outgoing *propagation*
directions, so ``g > 0`` scatters forward. The density is normalised over the sphere:

    p(mu) = (1 - g^2) / (4 pi (1 + g^2 - 2 g mu)^{3/2}),   integral over the sphere = 1.

Sampling uses the division-free forms of ``../shared/ALGORITHMS.md`` (``s = 2u - 1``, ``d = 1 + g s``)::

    1 - mu = (1-g)^2 (1-s) (2 + g(1+s)) / (2 d^2)
    1 + mu = (1+g)^2 (1+s) (2 - g(1-s)) / (2 d^2)
    pdf    = d^3 / (4 pi (1 - g^2)^2)

``sin(theta) = sqrt((1-mu)(1+mu))`` comes from those two products, so it keeps full relative precision for
``|g| -> 1``. ``mu`` itself is taken from the expanded polynomial
``mu = (s + g (3 + s^2)/2 + g^2 s + g^3 (s^2 - 1)/2) / d^2`` for ``|g| < 1/2`` (exactly ``s`` at ``g = 0``,
no division by ``g``) and from ``1 - (1 - mu)`` (``g >= 1/2``) or ``(1 + mu) - 1`` (``g <= -1/2``) otherwise.
The textbook inversion ``mu = (1 + g^2 - t^2) / (2 g)`` is not used (it loses all precision for small ``|g|``).
The local frame around the propagation direction is the branchless orthonormal basis of Duff et al. 2017.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

INV_4PI = 1.0 / (4.0 * math.pi)


def _as_g(g: float | Tensor, like: Tensor) -> Tensor:
    """``g`` as a float32 tensor broadcastable against ``like`` (scalar or per-ray ``(N,)``)."""
    return torch.as_tensor(g, dtype=torch.float32, device=like.device)


def hg_pdf(g: float | Tensor, cos_theta: Tensor) -> Tensor:
    """Henyey–Greenstein density per steradian.

    Args:
        g: asymmetry in ``(-1, 1)``, a float or a tensor broadcastable against ``cos_theta`` (e.g. ``(N,)``).
        cos_theta: ``mu``, cosine between the incoming and outgoing propagation directions, any shape.

    Returns:
        ``p(mu)`` with the broadcast shape of ``g`` and ``cos_theta``, float32.

    The denominator ``1 + g^2 - 2 g mu`` is evaluated as the sum of non-negative terms
    ``(1 - g)^2 + 2 g (1 - mu)`` (``g >= 0``) or ``(1 + g)^2 - 2 g (1 + mu)`` (``g < 0``), so no cancellation
    occurs beyond the one already present in ``mu``.
    """
    mu = cos_theta.to(torch.float32)
    g = _as_g(g, mu)
    one_m = (1.0 - mu).clamp(min=0.0)
    one_p = (1.0 + mu).clamp(min=0.0)
    denom = torch.where(g >= 0, (1.0 - g) ** 2 + 2.0 * g * one_m, (1.0 + g) ** 2 - 2.0 * g * one_p)
    return INV_4PI * (1.0 - g) * (1.0 + g) / (denom * denom.sqrt())


def orthonormal_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Branchless orthonormal basis (Duff et al. 2017) around unit vectors ``n`` ``(N, 3)``.

    Returns ``(t, b)``, each ``(N, 3)``, such that ``(t, b, n)`` is a right-handed orthonormal frame. Valid for
    every unit ``n`` (including ``n = (0, 0, -1)``: the sign is taken with ``copysign``, so ``-0`` counts as
    negative and ``sign + z`` never vanishes).
    """
    x, y, z = n.unbind(-1)
    sign = torch.copysign(torch.ones_like(z), z)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack((1.0 + sign * x * x * a, sign * b, -sign * x), dim=-1)
    bb = torch.stack((b, sign + y * y * a, -y), dim=-1)
    return t, bb


def hg_sample_cos(g: float | Tensor, u0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Sample the scattering cosine of the Henyey–Greenstein phase function.

    Args:
        g: asymmetry in ``(-1, 1)``: a float or a tensor broadcastable against ``u0``.
        u0: uniform numbers in ``[0, 1)``, any shape; ``s = 2 u0 - 1``.

    Returns:
        ``(mu, sin_theta, pdf)``: ``mu`` (exactly ``s`` at ``g = 0``), ``sin_theta = sqrt((1-mu)(1+mu))`` from the
        division-free forms (full relative precision as ``|g| -> 1``) and the density per steradian.
    """
    u0 = u0.to(torch.float32)
    g = _as_g(g, u0)
    s = 2.0 * u0 - 1.0
    # 1 -+ s straight from u0 (not from the rounded s) and d = 1 + g s as a sum of non-negative terms, so that
    # both stay accurate where they are small (s -> -1 with g -> 1, s -> 1 with g -> -1)
    one_ps = 2.0 * u0
    one_ms = 2.0 * (1.0 - u0)
    d = torch.where(g >= 0, (1.0 - g) + g * one_ps, (1.0 + g) - g * one_ms)
    d2 = d * d
    # 2 + g (1+s) and 2 - g (1-s), also as sums of non-negative terms for either sign of g
    pos = g >= 0
    fa = torch.where(pos, 2.0 + g * one_ps, 2.0 * (1.0 + g) - g * one_ms)
    fb = torch.where(pos, 2.0 * (1.0 - g) + g * one_ps, 2.0 - g * one_ms)
    one_minus_mu = (1.0 - g) ** 2 * one_ms * fa / (2.0 * d2)
    one_plus_mu = (1.0 + g) ** 2 * one_ps * fb / (2.0 * d2)
    g2 = g * g
    mu_poly = (s + 0.5 * g * (3.0 + s * s) + g2 * s + 0.5 * g2 * g * (s * s - 1.0)) / d2
    mu = torch.where(g >= 0.5, 1.0 - one_minus_mu, torch.where(g <= -0.5, one_plus_mu - 1.0, mu_poly))
    mu = mu.clamp(-1.0, 1.0)
    sin_theta = (one_minus_mu * one_plus_mu).clamp(min=0.0).sqrt()
    one_m_g2 = (1.0 - g) * (1.0 + g)
    pdf = INV_4PI * d2 * d / (one_m_g2 * one_m_g2)
    return mu, sin_theta, pdf


def hg_sample(g: float | Tensor, direction: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Sample an outgoing propagation direction from the Henyey–Greenstein phase function.

    Args:
        g: asymmetry in ``(-1, 1)``: a float or a per-ray ``(N,)`` tensor.
        direction: ``(N, 3)`` unit incoming propagation directions.
        u: ``(N, 2)`` uniform numbers in ``[0, 1)``; ``u[:, 0]`` picks ``mu`` (``s = 2 u0 - 1``), ``u[:, 1]``
            the azimuth ``2 pi u1``.

    Returns:
        ``(new_direction (N, 3), pdf (N,))``: unit outgoing propagation directions and their density per
        steradian, ``pdf = hg_pdf(g, mu)`` evaluated in the stable form ``d^3 / (4 pi (1 - g^2)^2)``.
        At ``g = 0`` the sampled ``mu`` equals ``s = 2 u0 - 1`` exactly.
    """
    direction = direction.to(torch.float32)
    u = u.to(torch.float32)
    mu, sin_theta, pdf = hg_sample_cos(g, u[:, 0])
    phi = (2.0 * math.pi) * u[:, 1]
    t, b = orthonormal_basis(direction)
    new_dir = (sin_theta * torch.cos(phi))[:, None] * t + (sin_theta * torch.sin(phi))[:, None] * b + mu[:, None] * direction
    return new_dir, pdf


def hg_sample_v3(g: float | Tensor, d: tuple[Tensor, Tensor, Tensor], u0: Tensor,
                 u1: Tensor) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor]:
    """:func:`hg_sample` in component form (directions as three ``(S,)`` tensors, ``g`` a float or a 0-d
    tensor): ``(new direction, pdf)``. Elementwise only, so a compiler fuses it into its caller."""
    mu, sin_t, pdf = hg_sample_cos(g, u0)
    x, y, z = d
    sign = torch.copysign(torch.ones_like(z), z)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = (1.0 + sign * x * x * a, sign * b, -sign * x)
    bb = (b, sign + y * y * a, -y)
    phi = (2.0 * math.pi) * u1
    c, s = sin_t * torch.cos(phi), sin_t * torch.sin(phi)
    return (c * t[0] + s * bb[0] + mu * x, c * t[1] + s * bb[1] + mu * y, c * t[2] + s * bb[2] + mu * z), pdf
