"""EM steps of the AR(2) velocity process at fixed orientations (calibration/velocity_em.py): the chain's
posterior mean against a dense least-squares solve of the same rows, and the EM property — the exact marginal
likelihood of the increments (Kalman filter, calibration/acc_rate.py) never decreases and the loop stops at a
fixed point."""

import copy

import numpy as np
import pytest

from imugraph.calibration.acc_rate import marginal_log_lik, process_matrices
from imugraph.calibration.velocity_ar2 import update_ar2
from imugraph.calibration.velocity_em import em_at_orientations, posterior_mean
from imugraph.factors.velocity import ar2_residuals
from imugraph.geometry import expmap
from imugraph.graphs.velocity_block import VelocityBlock

FREE_BOUNDS = ((0.01, 5.0), (0.05, 30.0))
G, DT = 9.81, 0.2


def _session(rng, K, a1=0.6, a2=0.05, q=0.002, noise=0.05):
    v = np.zeros((K, 3))
    for m in range(K - 2):
        v[m + 2] = a1 * v[m + 1] + a2 * v[m] + rng.normal(scale=np.sqrt(q), size=3)
    nRk = expmap(rng.normal(size=(K, 3)))
    c = v[1:] - v[:-1] + rng.normal(scale=noise, size=(K - 1, 3))
    dv = np.einsum("kji,kj->ki", nRk[:-1], c - np.array([0.0, 0.0, -G]) * DT)
    return VelocityBlock(dv, np.full(K - 1, noise), np.full(K - 1, DT), G), nRk, c


def test_posterior_mean_is_the_dense_least_squares_solution():
    rng = np.random.default_rng(1)
    K = 12
    block, nRk, c = _session(rng, K)
    block.ar2 = (0.5, 0.1, 0.004)
    s0 = np.zeros((K, 3))
    m = posterior_mean(block, nRk, s0)
    # rows: increments (v_{k+1} − v_k − c_k)/σ per axis, and the AR(2) rows (linear in v, ar2_residuals)
    J_ar = np.vstack([ar2_residuals(np.eye(K)[:, [j]], *block.ar2).ravel() for j in range(K)]).T
    D = (np.eye(K, k=1) - np.eye(K))[:-1] / block.sigma_dv[:, None]
    A = np.vstack([D, J_ar])
    for i in range(3):
        b = np.r_[c[:, i] / block.sigma_dv, np.zeros(K)]
        np.testing.assert_allclose(m[:, i], np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-9)


def _loglik(block, nRk, ar2):
    b = copy.copy(block)
    b.ar2 = ar2
    y = np.einsum("kij,kj->ki", nRk[:-1], b.dv) + np.array([0.0, 0.0, -G]) * DT
    K = b.n_keyframes
    return marginal_log_lik(np.zeros(1), y, b.sigma_dv**2, np.zeros(K - 1), np.ones(K - 1), *process_matrices(b))[0]


def test_em_at_fixed_orientations_climbs_the_marginal_likelihood_to_a_fixed_point():
    rng = np.random.default_rng(2)
    K = 600
    block, nRk, _ = _session(rng, K)
    start = (0.9, 0.0, 0.05)                     # far from the simulated (0.6, 0.05, 0.002)
    block.ar2 = start
    state = {"s": posterior_mean(block, nRk, np.zeros((K, 3))), "sigma": 0.5, "tau": 2.0, "ar2": start}

    def step(st, b):
        return update_ar2(st, b, nRk, None, *FREE_BOUNDS)

    lls = [_loglik(block, nRk, start)]
    for _ in range(4):                          # each call: 5 EM steps at these orientations
        b = copy.copy(block)
        b.ar2 = state["ar2"]
        em_at_orientations(state, b, nRk, step, iters=5, tol=0.0)
        lls.append(_loglik(block, nRk, state["ar2"]))
    # EM: non-decreasing up to the M-step's grid resolution (0.0005 in a)
    assert all(b >= a - 0.5 for a, b in zip(lls, lls[1:]))
    assert lls[-1] > lls[0] + 100.0
    b = copy.copy(block)
    b.ar2 = state["ar2"]
    em_at_orientations(state, b, nRk, step, iters=300, tol=1e-4)
    b.ar2 = state["ar2"]
    assert em_at_orientations(state, b, nRk, step, iters=2, tol=0.0) < 2e-3      # a fixed point
    a1, a2, q = state["ar2"]
    assert abs(a1 - 0.6) < 0.1 and abs(a2 - 0.05) < 0.1 and q == pytest.approx(0.002, rel=0.3)


def test_one_inner_step_is_the_plain_step():
    rng = np.random.default_rng(3)
    K = 50
    block, nRk, _ = _session(rng, K)
    calls = []

    def step(st, b):
        calls.append(b)
        return 0.25

    assert em_at_orientations({"s": np.zeros((K, 3)), "ar2": None}, block, nRk, step, iters=1) == 0.25
    assert calls == [block]
