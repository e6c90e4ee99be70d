"""The second-order (AR(2)) velocity process: stationary start against Yule–Walker, the block's
linearisation against its own cost (Jacobians), Takahashi's banded inverse against a dense inverse, the
M-step on exact moments, and EM recovering a simulated process through noisy accelerometer increments."""

import gtsam
import numpy as np
import pytest
from scipy.linalg import solveh_banded

from imugraph import keys
from imugraph.calibration.velocity_ar2 import fit_ar2, update_ar2
from imugraph.calibration.velocity_process import banded_inverse_bands, chain_bands, update_velocity_process
from imugraph.factors.robust import Kernel
from imugraph.factors.velocity import ar2_residuals, ar2_stationary
from imugraph.geometry import expmap
from imugraph.graphs.velocity_block import VelocityBlock

FREE = ((0.01, 5.0), np.exp(-0.2 / 30.0))        # σ bounds and φ_max of the "free" mode at Δt = 0.2 s


def _yule_walker(a1, a2, q):
    """γ_0, ρ_1 from the Yule–Walker equations ρ_1 = a_1 + a_2 ρ_1, ρ_2 = a_1 ρ_1 + a_2,
    γ_0 = q / (1 − a_1 ρ_1 − a_2 ρ_2) (independent of the closed form under test)."""
    rho1 = np.linalg.solve([[1.0 - a2]], [a1])[0]
    rho2 = a1 * rho1 + a2
    return q / (1.0 - a1 * rho1 - a2 * rho2), rho1, rho2


@pytest.mark.parametrize("a1,a2", [(0.9, 0.0), (-0.4, -0.6), (1.2, -0.5), (0.3, 0.4)])
def test_stationary_start_matches_yule_walker(a1, a2):
    gamma0, rho1 = ar2_stationary(a1, a2, 0.3)
    g_yw, r_yw, _ = _yule_walker(a1, a2, 0.3)
    assert gamma0 == pytest.approx(g_yw, rel=1e-12)
    assert rho1 == pytest.approx(r_yw, rel=1e-12)


def test_non_stationary_pair_is_refused():
    with pytest.raises(ValueError, match="stationary"):
        ar2_stationary(0.8, 0.3, 0.1)


def test_banded_inverse_matches_dense():
    rng = np.random.default_rng(1)
    K = 15
    M = np.zeros((K, K))
    for l in range(3):
        d = rng.normal(size=K - l)
        M += np.diag(d, -l) + (np.diag(d, l) if l else 0)
    M += 8.0 * np.eye(K)
    ab = np.stack([np.r_[np.diag(M, -l), np.zeros(l)] for l in range(3)])
    Z, Zd = banded_inverse_bands(ab), np.linalg.inv(M)
    for l in range(3):
        np.testing.assert_allclose(Z[l, :K - l], np.diag(Zd, -l), atol=1e-14)


def _block_values(rng, K, with_bias=False):
    nRk = expmap(rng.normal(size=(K, 3)))
    v = rng.normal(scale=0.5, size=(K, 6 if with_bias else 3))
    dv = rng.normal(size=(K - 1, 3))
    B = expmap(rng.normal(size=(K - 1, 3))) * 0.1 if with_bias else None
    block = VelocityBlock(dv, np.full(K - 1, 0.05), np.full(K - 1, 0.2), 9.81, kernel=Kernel("huber", 2.0),
                          B=B, bias_sigma0=0.2, bias_rw=0.01, ar2=(-0.4, -0.6, 0.2))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk[k]))
        values.insert(keys.vel(k), v[k])
    return block, values, nRk, v


@pytest.mark.parametrize("with_bias", [False, True])
def test_ar2_block_linearisation_is_gradient_of_cost(with_bias, assert_block_gradient):
    rng = np.random.default_rng(5)
    K = 8
    block, values, _, v = _block_values(rng, K, with_bias)
    key_list = [keys.rot(k) for k in range(K - 1)] + [keys.vel(k) for k in range(K)]
    assert_block_gradient(block, values, key_list)


def test_ar2_prior_is_the_exact_gaussian_density():
    # the prior's quadratic form equals the inverse of the AR(2) autocovariance matrix (Toeplitz, Yule–Walker)
    a1, a2, q, K = 1.1, -0.6, 0.05, 6
    g0, r1, r2 = _yule_walker(a1, a2, q)
    rho = [1.0, r1, r2]
    for _ in range(K - 3):
        rho.append(a1 * rho[-1] + a2 * rho[-2])
    Gamma = g0 * np.array([[rho[abs(i - j)] for j in range(K)] for i in range(K)])
    J = np.vstack([ar2_residuals(np.eye(K)[:, [c]], a1, a2, q).ravel() for c in range(K)]).T
    np.testing.assert_allclose(J.T @ J, np.linalg.inv(Gamma), rtol=1e-9, atol=1e-9)


def test_m_step_on_exact_moments_returns_the_process():
    a1, a2, q, N = -0.38, -0.64, 0.37, 3000
    g0, r1, r2 = _yule_walker(a1, a2, q)
    sxx = N * g0 * np.array([[1.0, r1], [r1, 1.0]])
    est = fit_ar2(N * g0, N * g0 * np.array([r1, r2]), sxx, N, *FREE)
    np.testing.assert_allclose(est[:2], (a1, a2), atol=1e-3)
    assert est[2] == pytest.approx(q, rel=1e-2)


def test_bounded_m_step_keeps_the_lag1_correlation_and_step_floor():
    # a slow drift (the rotation-only failure of the free estimate): bounded keeps ρ_1 ≤ φ_max, q ≥ floor
    a1, a2, q, N = 1.5, -0.52, 1e-4, 3000
    g0, r1, r2 = _yule_walker(a1, a2, q)
    phi_max = np.exp(-0.2 / 2.0)
    b1, b2, qb = fit_ar2(N * g0, N * g0 * np.array([r1, r2]), N * g0 * np.array([[1, r1], [r1, 1]]), N,
                         (0.5, 5.0), phi_max)
    assert b1 / (1 - b2) <= phi_max + 1e-12
    disc = b1**2 + 4 * b2                                # real roots: the slower one no slower than φ_max
    assert disc < 0 or (b1 + np.sqrt(disc)) / 2 <= phi_max + 1e-12
    assert qb >= 0.5**2 * (1 - phi_max**2) * (1 - 1e-12)
    assert np.sqrt(ar2_stationary(b1, b2, qb)[0]) >= 0.5 * (1 - 1e-9)


def test_bounded_m_step_refuses_persistence_moved_to_lag_two():
    # moments of a slow real-root process with ρ_1 at the bound (BROAD 04's "bounded_ar2" estimate before the
    # root bound: a = (0.18, 0.81)); the bounded fit must not keep its slow root 0.99
    a1, a2, q, N = 0.176, 0.806, 0.045, 3000
    g0, r1, r2 = _yule_walker(a1, a2, q)
    phi_max = np.exp(-0.2 / 2.0)
    b1, b2, _ = fit_ar2(N * g0, N * g0 * np.array([r1, r2]), N * g0 * np.array([[1, r1], [r1, 1]]), N,
                        (0.5, 5.0), phi_max)
    disc = b1**2 + 4 * b2
    assert disc < 0 or (b1 + np.sqrt(disc)) / 2 <= phi_max + 1e-12


def _simulate(rng, a1, a2, q, K):
    g0, r1, _ = _yule_walker(a1, a2, q)
    v = np.empty((K, 3))
    v[0] = rng.normal(scale=np.sqrt(g0), size=3)
    v[1] = r1 * v[0] + rng.normal(scale=np.sqrt(g0 * (1 - r1**2)), size=3)
    for k in range(1, K - 1):
        v[k + 1] = a1 * v[k] + a2 * v[k - 1] + rng.normal(scale=np.sqrt(q), size=3)
    return v


def _posterior_mean(block, nRk, K):
    """argmin of the block's (quadratic) cost over velocities at fixed orientations: Λ m = η with
    η_k = a (c_{k−1} − c_k), c_k the measured v_{k+1} − v_k."""
    c = np.array([0.0, 0.0, -block.g]) * block.dt_k[:, None] + np.einsum("kij,kj->ki", nRk[:-1], block.dv)
    a = 1.0 / block.sigma_dv[:, None] ** 2
    eta = np.zeros((K, 3)); eta[:-1] -= a * c; eta[1:] += a * c
    ab = chain_bands(block, nRk, np.zeros((K, 3)))
    return np.stack([solveh_banded(ab[:, :, i], eta[:, i], lower=True) for i in range(3)], axis=1)


def test_em_recovers_a_simulated_oscillating_process():
    # a hand moving back and forth (period ≈ 0.7 s at Δt = 0.2 s), seen through accelerometer increments
    # with noise comparable to the innovations; EM from the first-order start (σ_v 0.5 m/s, τ_v 2 s)
    rng = np.random.default_rng(7)
    a1, a2, q, K, dt = -0.38, -0.64, 0.1, 2500, 0.2
    v = _simulate(rng, a1, a2, q, K)
    nRk = expmap(rng.normal(size=(K, 3)))
    g = 9.81
    c = v[1:] - v[:-1] + rng.normal(scale=0.15, size=(K - 1, 3))        # measured velocity changes
    dv = np.einsum("kji,kj->ki", nRk[:-1], c - np.array([0.0, 0.0, -g]) * dt)   # body-frame increments
    block = VelocityBlock(dv, np.full(K - 1, 0.15), np.full(K - 1, dt), g, sigma_v=0.5, tau_v=2.0)
    state = {"sigma": 0.5, "tau": 2.0, "ar2": None}
    for _ in range(40):
        block.ar2 = state["ar2"]
        state["s"] = _posterior_mean(block, nRk, K)
        change = update_velocity_process(state, block, nRk, None, "free_ar2", 0.5, 2.0)
        if change < 1e-4:
            break
    a1_e, a2_e, q_e = state["ar2"]
    assert abs(a1_e - a1) < 0.05 and abs(a2_e - a2) < 0.05
    assert q_e == pytest.approx(q, rel=0.15)
    assert state["sigma"] == pytest.approx(np.sqrt(ar2_stationary(a1, a2, q)[0]), rel=0.1)


def test_update_ar2_skips_too_short_chains():
    state = {"s": np.zeros((4, 3)), "sigma": 0.5, "tau": 2.0, "ar2": None}
    block = VelocityBlock(np.zeros((3, 3)), np.full(3, 0.1), np.full(3, 0.2), 9.81)
    assert update_ar2(state, block, np.tile(np.eye(3), (4, 1, 1)), None, (0.5, 5.0), (0.05, 2.0)) == 0.0
    assert state["ar2"] is None


def test_ml_loop_recovers_simulated_oscillating_velocity():
    """A session whose keyframe velocities follow a known AR(2) process (linear in between, so Σ a dt between
    keyframes is exactly Δv): the ML loop with "free_ar2" settles near this realisation's own AR(2) fit."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.factors.gyro import keyframe_layout
    from imugraph.sim.motion import random_rotation_motion
    from imugraph.sim.sensors import SensorParams, simulate_imu

    rng = np.random.default_rng(11)
    rate, a1, a2, q = 50.0, -0.38, -0.64, 0.04
    motion = random_rotation_motion(120.0, rate, rng, rest_s=2.0)
    n = len(motion.t)
    kf, _ = keyframe_layout(n, 10)                                  # 5 Hz keyframes at 50 Hz
    ramp = np.clip(np.minimum(motion.t - 2.0, motion.t[-1] - 2.0 - motion.t) / 0.5, 0.0, 1.0)
    v_kf = _simulate(rng, a1, a2, q, len(kf)) * ramp[kf][:, None]
    v = np.stack([np.interp(motion.t, motion.t[kf], v_kf[:, i]) for i in range(3)], axis=1)
    n_acc = np.vstack([np.diff(v, axis=0) * rate, np.zeros((1, 3))])
    params = SensorParams(gyro_noise=np.full(3, 0.003), acc_noise=np.full(3, 0.03), mag_noise=np.full(3, 0.005))
    s = simulate_imu(motion.t, motion.nRb, motion.b_omega, n_acc, params, rng)
    est = calibrate(s, Options(estimate_velocity_process="free_ar2", gyro_map=False))
    assert np.array_equal(est.info["keyframe_samples"], kf)
    e1, e2, eq = next(h["velocity_ar2"] for h in reversed(est.info["history"]) if "velocity_ar2" in h)
    y, X = v_kf[2:].ravel(), np.stack([v_kf[1:-1].ravel(), v_kf[:-2].ravel()], axis=1)
    t12, *_ = np.linalg.lstsq(X, y, rcond=None)                     # the realisation's own fit
    tq = np.mean((y - X @ t12) ** 2)
    assert abs(e1 - t12[0]) < 0.08 and abs(e2 - t12[1]) < 0.08
    assert eq == pytest.approx(tq, rel=0.25)
