"""Per-sample robust kernels for the batched factors (iteratively reweighted least squares).

For a whitened residual r_j (3-vector) with norm s_j, the cost is ρ(s_j) and the Gauss–Newton weight is
w_j = ρ'(s_j)/s_j, the same linearisation GTSAM's `noiseModel.Robust` uses, but per sample instead of
per (batched) factor, so that one disturbed sample does not down-weight its whole keyframe.

    quadratic: ρ(s) = s²/2                                   w = 1
    huber:     ρ(s) = s²/2 (s ≤ k),  k s − k²/2 (s > k)     w = min(1, k/s)
    cauchy:    ρ(s) = k²/2 · log(1 + s²/k²)                 w = 1/(1 + s²/k²)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Kernel:
    name: str = "quadratic"
    k: float = 1.345

    def rho(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, float)
        if self.name == "quadratic":
            return 0.5 * s**2
        if self.name == "huber":
            return np.where(s <= self.k, 0.5 * s**2, self.k * s - 0.5 * self.k**2)
        if self.name == "cauchy":
            return 0.5 * self.k**2 * np.log1p((s / self.k) ** 2)
        raise ValueError(f"unknown robust kernel '{self.name}'")

    def weight(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, float)
        if self.name == "quadratic":
            return np.ones_like(s)
        if self.name == "huber":
            return np.minimum(1.0, self.k / np.maximum(s, 1e-12))
        if self.name == "cauchy":
            return 1.0 / (1.0 + (s / self.k) ** 2)
        raise ValueError(f"unknown robust kernel '{self.name}'")


QUADRATIC = Kernel("quadratic")
