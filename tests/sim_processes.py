"""Simulated random processes shared by the tests (not a test module)."""

from __future__ import annotations

import numpy as np


def gauss_markov_path(rng: np.random.Generator, K: int, dt: float, sigma: float, tau: float) -> np.ndarray:
    """(K, 3) stationary first-order Gauss–Markov path: x_0 ~ N(0, σ² I), x_{k+1} = φ x_k + σ √(1 − φ²) w_k,
    φ = exp(−Δt/τ) (the process of imugraph.factors.velocity.gauss_markov)."""
    phi = np.exp(-dt / tau)
    x = np.zeros((K, 3))
    x[0] = sigma * rng.standard_normal(3)
    for k in range(K - 1):
        x[k + 1] = phi * x[k] + sigma * np.sqrt(1 - phi**2) * rng.standard_normal(3)
    return x
