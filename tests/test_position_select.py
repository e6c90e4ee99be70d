"""σ_p of the bounded position per recording (task J): the (v, p) chain's precision (J1), the EM M-step, the
prior normaliser of (J2), and the Laplace selection switching itself off for a travelling sensor."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.calibration.position_process import m_step, posterior_vp, vp_bands
from imugraph.calibration.position_select import choose, prior_half_logdet
from imugraph.graphs.velocity_block import VelocityBlock
from sim_processes import gauss_markov_path


def _block(K=6, seed=0):
    rng = np.random.default_rng(seed)
    dt = 0.2 + 0.05 * rng.random(K - 1)
    blk = VelocityBlock(dv=rng.normal(size=(K - 1, 3)), sigma_dv=0.05 + 0.02 * rng.random(K - 1), dt_k=dt, g=9.81,
                        sigma_v=0.5, tau_v=2.0)
    blk.fixed_weights = np.ones(K - 1)
    return blk, np.tile(np.eye(3), (K, 1, 1)), np.zeros((K, 3))


def _dense(ab: np.ndarray) -> np.ndarray:
    n = ab.shape[1]
    A = np.zeros((n, n))
    for i in range(ab.shape[0]):
        for j in range(n - i):
            A[j + i, j] = A[j, j + i] = ab[i, j]
    return A


def _written_out(blk, sigma_p, tau_p, sigma_kin, data=True):
    """One axis' precision over (v_0, p_0, v_1, p_1, …), every term added as its own outer product."""
    K = blk.n_keyframes
    L = np.zeros((2 * K, 2 * K))

    def add(idx, coef, prec):
        c = np.zeros(2 * K)
        c[idx] = coef
        L[:] += prec * np.outer(c, c)

    add([0], [1.0], 1.0 / blk.sigma_v**2)
    add([1], [1.0], 1.0 / sigma_p**2)
    for k, dt in enumerate(blk.dt_k):
        v0, p0, v1, p1 = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
        if data:
            add([v0, v1], [-1.0, 1.0], 1.0 / blk.sigma_dv[k] ** 2)            # v_{k+1} − v_k = c_k
        phi_v = np.exp(-dt / blk.tau_v)
        add([v0, v1], [-phi_v, 1.0], 1.0 / (blk.sigma_v**2 * (1 - phi_v**2)))   # velocity Gauss–Markov
        add([v0, p0, p1], [-dt, -1.0, 1.0], 1.0 / sigma_kin**2)                 # (P1) kinematics
        phi = np.exp(-dt / tau_p)
        add([p0, p1], [-phi, 1.0], 1.0 / (sigma_p**2 * (1 - phi**2)))           # (P1) prior
    return L


def test_vp_bands_equal_the_terms_written_out():
    blk, nRk, s = _block()
    got = _dense(vp_bands(blk, nRk, s, 0.7, 30.0, sigma_kin=0.01))
    np.testing.assert_allclose(got, _written_out(blk, 0.7, 30.0, 0.01), rtol=1e-10, atol=1e-8)


def test_prior_half_logdet_is_that_of_the_prior_alone():
    blk, nRk, s = _block(K=7, seed=3)
    want = 3 * 0.5 * np.linalg.slogdet(_written_out(blk, 1.3, 20.0, 1e-3, data=False))[1]
    assert prior_half_logdet(blk, nRk, s, 1.3, 20.0) == pytest.approx(want, rel=1e-9)


def test_posterior_mean_solves_the_dense_normal_equations():
    blk, nRk, s = _block(K=8, seed=5)
    L = _written_out(blk, 0.5, 30.0, 1e-3)
    # right-hand side of the increments ½ a_k |v_{k+1} − v_k − c_k|², c_k = R_k Δv_k + n_grav Δt_k (x axis)
    c = blk.dv[:, 0]
    eta = np.zeros(2 * blk.n_keyframes)
    for k, ck in enumerate(c):
        a = 1.0 / blk.sigma_dv[k] ** 2
        eta[2 * k] -= a * ck
        eta[2 * k + 2] += a * ck
    x = np.linalg.solve(L, eta)
    v, p = posterior_vp(blk, nRk, s, 0.5, 30.0)
    np.testing.assert_allclose(v[:, 0], x[0::2], atol=1e-8)
    np.testing.assert_allclose(p[:, 0], x[1::2], atol=1e-8)


def test_m_step_recovers_the_sigma_of_a_long_simulated_process():
    rng = np.random.default_rng(1)
    K, dt, tau, sigma = 20000, 0.2, 30.0, 0.8
    p = gauss_markov_path(rng, K, dt, sigma, tau)
    got = m_step(p, np.zeros(K), np.zeros(K - 1), np.full(K - 1, dt), tau)
    assert got == pytest.approx(sigma, rel=0.1)


def test_choose_prefers_the_looser_bound_within_the_margin():
    scores = [{"sigma_p": 1e4, "log_z": -10.0}, {"sigma_p": 1.0, "log_z": -9.5}, {"sigma_p": 0.1, "log_z": -12.0}]
    assert choose(scores)["sigma_p"] == 1.0
    assert choose(scores, margin=1.0)["sigma_p"] == 1e4


def test_laplace_selection_switches_off_for_a_walk():
    """A simulated 60 s walk (≈ 70 m): the bound must not be chosen (benchmarks/j2_travel.py, shorter)."""
    from benchmarks.j2_travel import travel_session
    from imugraph.calibration.ml import Options, calibrate

    s, path = travel_session(1, "walk", duration_s=60.0)
    assert np.ptp(path[:, :2], axis=0).max() > 20.0
    est = calibrate(s, Options(position_select=(1e4, 1.0, 0.1), position_select_rounds=True), allow_weak=True)
    assert est.info["position_sigma"] is None
    plain = calibrate(s, Options(), allow_weak=True)          # "off" chosen: exactly the defaults' result
    np.testing.assert_array_equal(est.quat, plain.quat)
