"""Counter-based random numbers from an integer hash (stateless, compiles into fused kernels).

A random number is a pure function of ``(key, counter, lane)``: no generator state is carried, so a batch of
paths can draw its numbers inside a ``torch.compile``'d step and the result depends only on each path's own
key and counter (not on the batch layout or the number of slots). Same key, counter and lane => same number
on every device.

Hash: Chris Wellons' ``lowbias32`` family, constants ``[16 21f0aaad 15 735a2d97 15]`` (both multipliers below
2^31, so every product of a 32-bit value fits in int64 without overflow). All arithmetic is on int64 tensors
holding values in ``[0, 2^32)``.

:class:`RandomSource` wraps a ``torch.Generator`` for the randomness that is not per path (the NRC frame's
training positions, the queued shadow rays' estimators) and carries the per-path function, so a test can script
both.

Uniforms: the top 24 bits of a hash, ``u = (h >> 8) * 2^-24``, exactly representable in float32 and in
``[0, 1 - 2^-24]`` (so ``-log1p(-u)`` is always finite).
"""

from __future__ import annotations

import torch
from torch import Tensor

MASK32 = 0xFFFFFFFF
_M1 = 0x21F0AAAD
_M2 = 0x735A2D97
_GOLDEN = 0x9E3779B9  # 2^32 / phi: decorrelates lanes and seeds
_INV_2_24 = 1.0 / (1 << 24)
# Eager draws of up to this many numbers hash all their lanes at once: 1.1-5.6x faster at 128-1,024 paths (2-18
# lanes, one thread), slower from ~2^15 numbers on (0.4-0.9x at 4,096 x 18 and 16,384 x 4), where the per-lane form
# stays.
EAGER_LANES_MAX = 1 << 14


def hash32(x: Tensor) -> Tensor:
    """A bijective 32-bit integer hash of an int64 tensor (taken modulo 2^32); returns int64 in ``[0, 2^32)``."""
    x = x & MASK32
    x = x ^ (x >> 16)
    x = (x * _M1) & MASK32
    x = x ^ (x >> 15)
    x = (x * _M2) & MASK32
    return x ^ (x >> 15)


def path_key(seed: int, sample_id: Tensor) -> Tensor:
    """The per-path key ``(N,)`` int64 for camera sample ids ``(N,)`` (int64, any value) under ``seed``."""
    s = hash32(torch.full_like(sample_id, (int(seed) * _GOLDEN) & MASK32))
    lo = hash32(sample_id ^ s)
    return hash32(lo + hash32((sample_id >> 32) + s))


def uniforms(key: Tensor, counter: Tensor, lanes: int) -> list[Tensor]:
    """``lanes`` float32 uniforms ``(N,)`` in ``[0, 1)`` for keys and counters ``(N,)`` (int64), one tensor a
    lane (elementwise code only, so a compiler fuses it with its consumers).

    Lane ``j`` of the draw ``(key, counter)`` is ``hash32(hash32(key ^ hash32(counter)) ^ (j + 1) * golden)``:
    streams of different keys never shift into each other (unlike ``hash(key + counter)``).
    """
    s = hash32(key ^ hash32(counter))
    if lanes > 1 and not torch.compiler.is_compiling() and s.numel() * lanes <= EAGER_LANES_MAX:
        # Eager code at a few paths pays per op, not per number: all lanes in one hash over (lanes, N), the same
        # integers. Compiled code (and export) keeps one expression a lane, which a compiler fuses; it never reads
        # the batch size here (a symbolic size compared with a constant would specialise the graph).
        salt = (torch.arange(1, lanes + 1, dtype=torch.int64, device=s.device) * _GOLDEN) & MASK32
        return list(((hash32(s[None] ^ salt[:, None]) >> 8).to(torch.float32) * _INV_2_24).unbind(0))
    return [(hash32(s ^ (((j + 1) * _GOLDEN) & MASK32)) >> 8).to(torch.float32) * _INV_2_24 for j in range(lanes)]


class RandomSource:
    """Uniforms in ``[0, 1)`` from ``generator`` on ``device``."""

    # Per-path counter-based uniforms ``(key, counter, lanes) -> lanes x (N,)`` of the transport step
    # (:func:`nrc.transport.rng.uniforms`); a scripted source replaces it too.
    counter_uniforms = staticmethod(uniforms)

    def __init__(self, generator: torch.Generator, device: torch.device | str, seed: int = 0) -> None:
        self.generator = generator
        self.device = torch.device(device)
        self.seed = int(seed)  # keys of the per-path streams: nrc.transport.rng.path_key(seed, path id)

    @classmethod
    def seeded(cls, seed: int, device: torch.device | str) -> RandomSource:
        return cls(torch.Generator(device=device).manual_seed(int(seed)), device, int(seed))

    def rand(self, n: int, k: int) -> Tensor:
        """``(n, k)`` float32 uniforms."""
        return torch.rand(n, k, generator=self.generator, device=self.device)
