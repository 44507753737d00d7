"""The source of uniform random numbers of a renderer: a ``torch.Generator`` behind one small interface.

Renderers draw every uniform through :meth:`RandomSource.rand` (and hand :attr:`RandomSource.generator`
to the transmittance estimators), so a test can replace the stream by a scripted one and follow a path
by hand. Same seed, same config, same device: same numbers.
"""

from __future__ import annotations

import torch
from torch import Tensor


class RandomSource:
    """Uniforms in ``[0, 1)`` from ``generator`` on ``device``."""

    def __init__(self, generator: torch.Generator, device: torch.device | str) -> None:
        self.generator = generator
        self.device = torch.device(device)

    @classmethod
    def seeded(cls, seed: int, device: torch.device | str) -> RandomSource:
        return cls(torch.Generator(device=device).manual_seed(int(seed)), device)

    def rand(self, n: int, k: int) -> Tensor:
        """``(n, k)`` float32 uniforms."""
        return torch.rand(n, k, generator=self.generator, device=self.device)
