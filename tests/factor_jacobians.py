"""Shared check for the tests: a factor's analytic Jacobians (through gtsam's linearize) against central differences
of its whitened error over each key's tangent space."""

import gtsam
import numpy as np


def assert_jacobians_match_numerical(f, v: gtsam.Values, keys: list, dims: list[int], eps: float = 1e-6,
                                     atol: float = 1e-6) -> np.ndarray:
    """A of f.linearize(v) equals (e(x ⊕ h eᵢ) − e(x ⊖ h eᵢ)) / 2h column by column, keys in f's order with
    tangent dimensions `dims`. Returns A (for further checks)."""
    A, _ = f.linearize(v).jacobian()

    def moved(key, i, h):
        delta = gtsam.VectorValues()
        for kk, dd in zip(keys, dims):
            step = np.zeros(dd)
            if kk == key:
                step[i] = h
            delta.insert(kk, step)
        return f.whitenedError(v.retract(delta))

    col = 0
    for key, d in zip(keys, dims):
        for i in range(d):
            np.testing.assert_allclose(A[:, col + i], (moved(key, i, eps) - moved(key, i, -eps)) / (2 * eps), atol=atol)
        col += d
    return A
