"""The issue-2d evidence functions of benchmarks/rasteiro.py on data with a known answer.

A constant field seen through a known affine map: the oracle fit (truth orientation known) must recover
it (residual at the noise level, calibrated norm ≈ 1), the norm-only optimum must reach the noise level; a
field that varies with time must leave the oracle a residual of its size.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.rasteiro import best_affine_norm_error, oracle_affine_fit  # noqa: E402
from imugraph.geometry import expmap  # noqa: E402


def _rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.stack([expmap(w) for w in rng.normal(0.0, 1.5, (n, 3))])


def _distorted(nRb: np.ndarray, n_mag: np.ndarray, rng: np.random.Generator, sigma: float):
    D = np.array([[1.2, 0.05, -0.03], [0.0, 0.9, 0.04], [0.02, -0.06, 1.1]]) * 30.0
    o = np.array([5.0, -8.0, 12.0])
    b_dir = np.einsum("kji,kj->ki", nRb, n_mag)           # bRn·n_mag per sample
    return b_dir @ D.T + o + sigma * 30.0 * rng.standard_normal(b_dir.shape), D, o


def test_oracle_recovers_a_constant_field_model():
    rng = np.random.default_rng(3)
    nRb = _rotations(1500, rng)
    n_mag = np.tile([0.35, 0.0, -0.94] / np.linalg.norm([0.35, 0.0, -0.94]), (1500, 1))
    y, _, _ = _distorted(nRb, n_mag, rng, sigma=0.002)
    vec, norm = oracle_affine_fit(y, nRb)
    assert vec < 0.006
    assert norm < 0.004


def test_oracle_residual_shows_a_varying_field():
    rng = np.random.default_rng(4)
    nRb = _rotations(1500, rng)
    base = np.array([0.35, 0.0, -0.94]) / np.linalg.norm([0.35, 0.0, -0.94])
    wobble = 0.05 * np.sin(np.linspace(0, 6 * np.pi, 1500))[:, None] * np.array([1.0, 1.0, 0.0])
    y, _, _ = _distorted(nRb, base + wobble, rng, sigma=0.002)
    vec, _ = oracle_affine_fit(y, nRb)
    assert vec > 0.02                       # the 5 % wobble cannot be explained by D, o


def test_norm_floor_reaches_noise_level_on_an_ellipsoid():
    rng = np.random.default_rng(5)
    nRb = _rotations(2000, rng)
    n_mag = np.tile([0.0, 0.6, -0.8], (2000, 1))
    y, D, o = _distorted(nRb, n_mag, rng, sigma=0.003)
    C0 = np.linalg.inv(D) * 1.05                           # a start 5 % off, offset 1 unit off
    floor = best_affine_norm_error(y, C0, o + 1.0)
    assert np.isfinite(floor) and floor < 0.005
