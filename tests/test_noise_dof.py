"""Degrees of freedom absorbed by the field perturbation (imugraph.calibration.noise.field_dof), against
dense linear algebra computed here independently."""

import numpy as np

from imugraph.calibration.noise import field_dof, tridiagonal_inverse_diagonal


def _dense_tridiagonal(diag, off):
    return np.diag(diag) + np.diag(off, 1) + np.diag(off, -1)


def test_tridiagonal_inverse_diagonal_matches_dense_inverse():
    rng = np.random.default_rng(3)
    off = rng.normal(size=39)
    diag = np.abs(off).sum() * 0 + 2.5 + rng.uniform(0, 3, 40)
    diag[:-1] += np.abs(off)
    diag[1:] += np.abs(off)        # diagonally dominant: positive definite
    A = _dense_tridiagonal(diag, off)
    assert np.allclose(tridiagonal_inverse_diagonal(diag, off), np.diag(np.linalg.inv(A)), rtol=1e-10)


def test_field_dof_is_the_hat_matrix_trace_of_the_gauss_markov_smoother():
    rng = np.random.default_rng(4)
    K, tau = 30, 1.0
    dt = np.full(K - 1, 0.2)
    sigma = (0.015, 0.003, 0.01)
    G_dd = np.zeros((K, 3, 3))
    h = rng.uniform(1e3, 1e5, (K, 3))
    G_dd[:, [0, 1, 2], [0, 1, 2]] = h
    expected = 0.0
    phi = np.exp(-dt / tau)
    for a in range(3):          # Q_a from the GM definition: d0 ~ N(0, σ²), d_{k+1} − φ d_k ~ N(0, σ²(1 − φ²))
        L = np.zeros((K, K))
        L[0, 0] = 1 / sigma[a]
        for k in range(K - 1):
            s = sigma[a] * np.sqrt(1 - phi[k] ** 2)
            L[k + 1, k], L[k + 1, k + 1] = -phi[k] / s, 1 / s
        Q = L.T @ L
        H = np.diag(h[:, a])
        expected += np.trace(H @ np.linalg.inv(H + Q))
    got = field_dof(G_dd, dt, sigma, tau)
    assert np.isclose(got, expected, rtol=1e-9)
    assert 0 < got < 3 * K


def test_field_dof_vanishes_without_data_and_saturates_with_strong_data():
    K, dt = 20, np.full(19, 0.2)
    assert field_dof(np.zeros((K, 3, 3)), dt, 0.015, 1.0) == 0.0
    strong = np.tile(np.eye(3) * 1e14, (K, 1, 1))
    assert np.isclose(field_dof(strong, dt, 0.015, 1.0), 3 * K, rtol=1e-6)
