"""Packing of the magnetometer calibration vector θ = (vec D, o, δ) (13,)."""

from __future__ import annotations

import numpy as np

THETA_DIM = 13
SLICE_D = slice(0, 9)
SLICE_O = slice(9, 12)
INDEX_DIP = 12


def pack_theta(D: np.ndarray, o: np.ndarray, dip_rad: float) -> np.ndarray:
    return np.concatenate([np.asarray(D, float).reshape(9), np.asarray(o, float).reshape(3), [float(dip_rad)]])


def unpack_theta(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    theta = np.asarray(theta, float).reshape(THETA_DIM)
    return theta[SLICE_D].reshape(3, 3), theta[SLICE_O].copy(), float(theta[INDEX_DIP])
