"""The source of uniform random numbers of a renderer: a ``torch.Generator`` behind one small interface.

Renderers draw every uniform through :meth:`RandomSource.rand` (and hand :attr:`RandomSource.generator`
to the transmittance estimators), so a test can replace the stream by a scripted one and follow a path
by hand. Same seed, same config, same device: same numbers.
"""

from __future__ import annotations

import torch
from torch import Tensor

from nrc.transport.rng import uniforms


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
