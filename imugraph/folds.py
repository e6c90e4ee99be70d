"""Interleaved time blocks for K-fold held-out scoring (the calibration's field/gyro-map selection and the
diagnosis' attribution share them): block b = ⌊(t − t0)/block_s⌋ belongs to fold b mod K, so every fold holds
out samples spread over the whole recording."""

from __future__ import annotations

import numpy as np


def time_blocks(t: np.ndarray, block_s: float, t0: float | None = None) -> np.ndarray:
    """(N,) int block index ⌊(t − t0)/block_s⌋ of each sample (t0: t[0] when None)."""
    t = np.asarray(t, float)
    return np.floor((t - (t[0] if t0 is None else t0)) / block_s).astype(int)


def held_out_masks(t: np.ndarray, block_s: float, n_folds: int, t0: float | None = None) -> list[np.ndarray]:
    """K (N,) bool masks: True where fold k holds the sample out (its block index mod K equals k)."""
    block = time_blocks(t, block_s, t0)
    return [(block % n_folds) == k for k in range(n_folds)]
