"""The one transform between linear HDR radiance and the generator's range [-1, 1].

    encode(x) = 2 * log1p(clip(x, 0, max_value) / scale) / log1p(max_value / scale) - 1
    decode(y) = scale * expm1((clip(y, -1, 1) + 1) / 2 * log1p(max_value / scale))

A log curve gives the dark indirect light of a GI map as many levels as its bright spots; it is
exactly invertible on [0, max_value] (values above ``max_value`` are clipped, negatives are 0).
Both work on numpy arrays and torch tensors (elementwise, any shape). Used for the GI target and
the DL input; the generator's tanh output goes through ``decode`` to give linear HDR GI.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class HDRTransform:
    """Linear HDR <-> [-1, 1] (module doc).

    Attributes:
        scale: radiance where the curve turns from linear to logarithmic (> 0).
        max_value: largest radiance represented (> 0); larger values are clipped to it.
    """

    scale: float = 0.25
    max_value: float = 64.0

    def __post_init__(self) -> None:
        for name in ("scale", "max_value"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"HDRTransform.{name} must be a finite number > 0, got {v!r}")

    @property
    def _norm(self) -> float:
        return math.log1p(self.max_value / self.scale)

    def encode(self, x: Any) -> Any:
        """Linear HDR (>= 0) -> [-1, 1]; numpy array or torch tensor of any shape."""
        if _is_torch(x):
            return 2.0 * (x.clamp(0.0, self.max_value) / self.scale).log1p() / self._norm - 1.0
        import numpy as np

        a = np.clip(np.asarray(x, np.float32), 0.0, self.max_value)
        return (2.0 * np.log1p(a / self.scale) / self._norm - 1.0).astype(np.float32)

    def decode(self, y: Any) -> Any:
        """[-1, 1] -> linear HDR in [0, max_value]; numpy array or torch tensor of any shape."""
        if _is_torch(y):
            return self.scale * ((y.clamp(-1.0, 1.0) + 1.0) * 0.5 * self._norm).expm1()
        import numpy as np

        a = np.clip(np.asarray(y, np.float32), -1.0, 1.0)
        return (self.scale * np.expm1((a + 1.0) * 0.5 * self._norm)).astype(np.float32)


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


__all__ = ["HDRTransform"]
