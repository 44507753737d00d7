"""What a renderer returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class RenderResult:
    """A rendered image and the renderer's measurements.

    Attributes:
        image: ``(H, W, 3)`` float32 linear RGB, row 0 at the top; never NaN or Inf.
        metrics: JSON-serialisable numbers (timings in seconds, sample rates, ...) for ``metrics.json``.
    """

    image: np.ndarray
    metrics: dict[str, Any] = field(default_factory=dict)
