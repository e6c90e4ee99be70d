"""ML parameters of the velocity process (imugraph.calibration.velocity_process): the chain covariances
against a dense inverse of the block's own Hessian, the Gauss–Markov fit against simulated chains with
known σ_v/τ_v and against the AR(1) closed form, and the whole ML loop recovering a simulated process."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.calibration.velocity_process import (ar1_closed_form, banded_inverse_bands, chain_covariance,
                                                   fit_gauss_markov, moments)
from imugraph.factors.robust import Kernel
from imugraph.geometry import expmap
from imugraph.graphs.velocity_block import VelocityBlock


def _ar1(rng, dt_k, sigma, tau):
    """(K, 3) Gauss–Markov chain sampled exactly at the given intervals (independent of the code under test:
    v_{k+1} = e^{−Δt/τ} v_k + σ √(1 − e^{−2Δt/τ}) n_k)."""
    v = np.empty((len(dt_k) + 1, 3))
    v[0] = sigma * rng.standard_normal(3)
    for k, dt in enumerate(dt_k):
        a = np.exp(-dt / tau)
        v[k + 1] = a * v[k] + sigma * np.sqrt(1 - a * a) * rng.standard_normal(3)
    return v


def test_band_inverse_of_a_tridiagonal_matches_dense_inverse():
    rng = np.random.default_rng(1)
    K = 9
    off = rng.uniform(-1.0, 0.0, K - 1)
    diag = np.abs(np.r_[off, 0]) + np.abs(np.r_[0, off]) + rng.uniform(0.1, 1.0, K)   # diagonally dominant
    A = np.diag(diag) + np.diag(off, 1) + np.diag(off, -1)
    Z = np.linalg.inv(A)
    P, C = banded_inverse_bands(np.vstack([diag, np.r_[off, 0.0]]))     # lower form, bandwidth 1
    C = C[:-1]
    np.testing.assert_allclose(P, np.diag(Z), rtol=1e-10)
    np.testing.assert_allclose(C, np.diag(Z, 1), rtol=1e-10)


@pytest.mark.parametrize("with_rest,per_axis", [(False, False), (True, False), (False, True)])
def test_chain_covariance_is_inverse_of_block_hessian(with_rest, per_axis):
    """Orientations held: the velocity part of the block's Gauss–Newton Hessian is Λ ⊗ I₃ (Huber weights
    included); its dense inverse gives the per-axis bands."""
    rng = np.random.default_rng(2)
    K = 8
    nRk = expmap(rng.normal(size=(K, 3)))
    v = rng.normal(scale=0.5, size=(K, 3))
    dv = rng.normal(scale=1.0, size=(K - 1, 3))
    dt_k = rng.uniform(0.1, 0.3, K - 1)
    rest = np.array([True, False, False, True, False, False, False, True]) if with_rest else None
    sigma_v, tau_v = (np.array([0.7, 0.7, 1.3]), np.array([0.8, 0.8, 0.3])) if per_axis else (0.7, 0.8)
    block = VelocityBlock(dv, np.full(K - 1, 0.3), dt_k, 9.81, sigma_v=sigma_v, tau_v=tau_v,
                          kernel=Kernel("huber", 2.0), rest=rest)
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk[k]))
        values.insert(keys.vel(k), v[k])
    r, *_ = block.terms(nRk, v)
    assert np.any(np.linalg.norm(r, axis=1) > 2.0)          # some intervals are down-weighted by Huber
    vel_keys = [keys.vel(k) for k in range(K)]
    order = gtsam.Ordering([keys.rot(k) for k in range(K - 1)] + vel_keys)
    H = block.linearize(values).augmentedHessian(order)[:-1, :-1]
    Hvv = H[3 * (K - 1):, 3 * (K - 1):]
    Z = np.linalg.inv(Hvv)
    P, C = chain_covariance(block, nRk, v)
    for axis in range(3):
        np.testing.assert_allclose(P[:, axis], np.diag(Z)[axis::3], rtol=1e-8)
        np.testing.assert_allclose(C[:, axis], np.diag(Z, 3)[axis::3], rtol=1e-8)


@pytest.mark.parametrize("sigma,tau", [(0.4, 0.6), (1.2, 3.0), (0.1, 0.25)])
def test_fit_recovers_simulated_gauss_markov(sigma, tau):
    rng = np.random.default_rng(3)
    dt_k = rng.uniform(0.15, 0.25, 6000)                    # uneven keyframe spacing
    v = _ar1(rng, dt_k, sigma, tau)
    s_hat, t_hat = fit_gauss_markov(*moments(v), dt_k)
    assert abs(s_hat / sigma - 1) < 0.05
    assert abs(t_hat / tau - 1) < 0.08


def test_profile_ml_agrees_with_ar1_closed_form_on_uniform_spacing():
    rng = np.random.default_rng(4)
    dt_k = np.full(5000, 0.2)
    v = _ar1(rng, dt_k, 0.5, 0.7)
    s0, s1 = moments(v)
    closed = ar1_closed_form(s0, s1, 0.2)
    fitted = fit_gauss_markov(s0, s1, dt_k)
    np.testing.assert_allclose(fitted, closed, rtol=0.01)    # they differ only by the v_0 term, O(1/K)


def test_posterior_covariance_term_unbiases_noisy_means():
    """A chain seen through noise: the smoothed means alone under-state σ_v; means plus the posterior
    covariance recover it (the EM moments). Smoothing done densely here, independently of the module."""
    rng = np.random.default_rng(5)
    K, dt, sigma, tau, noise = 1500, 0.2, 0.5, 0.8, 0.4
    v = _ar1(rng, np.full(K - 1, dt), sigma, tau)[:, 0]
    y = v + noise * rng.standard_normal(K)
    phi = np.exp(-dt / tau)
    q = sigma**2 * (1 - phi**2)
    Lam = np.zeros((K, K))                                 # prior precision of the chain + observations
    Lam[0, 0] += 1 / sigma**2
    for k in range(K - 1):
        Lam[np.ix_([k, k + 1], [k, k + 1])] += np.array([[phi**2, -phi], [-phi, 1.0]]) / q
    Lam += np.eye(K) / noise**2
    Z = np.linalg.inv(Lam)
    m = Z @ (y / noise**2)
    s_means, _ = fit_gauss_markov(*moments(m[:, None]), np.full(K - 1, dt))
    s_em, t_em = fit_gauss_markov(*moments(m[:, None], np.diag(Z)[:, None], np.diag(Z, 1)[:, None]),
                                  np.full(K - 1, dt))
    truth = float(np.sqrt(np.mean(v**2)))
    assert s_means < 0.9 * truth
    assert abs(s_em / truth - 1) < 0.1 and abs(t_em / tau - 1) < 0.3


def test_ml_loop_recovers_simulated_velocity_process():
    """A session whose velocity is a known Gauss–Markov process: the ML loop with
    estimate_velocity_process settles near its σ_v and τ_v (start values 0.5 m/s, 2 s)."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.sim.motion import random_rotation_motion
    from imugraph.sim.sensors import SensorParams, simulate_imu

    rng = np.random.default_rng(6)
    rate, sigma, tau = 50.0, 0.3, 0.6
    motion = random_rotation_motion(120.0, rate, rng, rest_s=2.0)
    n = len(motion.t)
    # the process inside the motion, still at the rests (which give the initial noise levels), 0.5-s ramps
    ramp = np.clip(np.minimum(motion.t - 2.0, motion.t[-1] - 2.0 - motion.t) / 0.5, 0.0, 1.0)
    v = _ar1(rng, np.full(n - 1, 1 / rate), sigma, tau) * ramp[:, None]
    n_acc = np.vstack([np.diff(v, axis=0) * rate, np.zeros((1, 3))])   # Σ a dt between keyframes = Δv
    params = SensorParams(gyro_noise=np.full(3, 0.003), acc_noise=np.full(3, 0.03), mag_noise=np.full(3, 0.005))
    s = simulate_imu(motion.t, motion.nRb, motion.b_omega, n_acc, params, rng)
    est = calibrate(s, Options(estimate_velocity_process="free", gyro_map=False))
    kf = est.info["keyframe_samples"]
    # this realisation's own ML values, from the true velocities at the keyframes
    truth_sigma, truth_tau = fit_gauss_markov(*moments(v[kf]), np.diff(s.t[kf]))
    assert abs(truth_tau / tau - 1) < 0.3                  # the realisation is near the process asked for
    assert abs(est.info["velocity_sigma"] / truth_sigma - 1) < 0.15
    assert abs(est.info["velocity_tau"] / truth_tau - 1) < 0.2


def _chain_nll(v, dt_k, sigma, tau):
    """−log density of a Gauss–Markov chain written out term by term (independent of the module)."""
    var0 = sigma**2
    nll = 0.5 * np.sum(v[0] ** 2) / var0 + 1.5 * np.log(2 * np.pi * var0)
    for k, dt in enumerate(dt_k):
        a = np.exp(-dt / tau)
        var = sigma**2 * (1 - a * a)
        nll += 0.5 * np.sum((v[k + 1] - a * v[k]) ** 2) / var + 1.5 * np.log(2 * np.pi * var)
    return nll


@pytest.mark.parametrize("sigma_bounds,tau_bounds", [((0.01, 5.0), (0.05, 30.0)), ((0.6, 5.0), (0.05, 30.0)),
                                                     ((0.01, 5.0), (0.05, 0.3))])
def test_fit_is_the_constrained_maximum_of_the_chain_density(sigma_bounds, tau_bounds):
    """Against a grid over (σ, τ) of the term-by-term chain density, inside the bounds (active or not)."""
    rng = np.random.default_rng(7)
    dt_k = rng.uniform(0.15, 0.25, 300)
    v = _ar1(rng, dt_k, 0.4, 0.6)
    sig, tau = fit_gauss_markov(*moments(v), dt_k, tau_bounds, sigma_bounds)
    assert sigma_bounds[0] - 1e-9 <= sig <= sigma_bounds[1] and tau_bounds[0] - 1e-6 <= tau <= tau_bounds[1] + 1e-6
    best = _chain_nll(v, dt_k, sig, tau)
    for s in np.geomspace(*np.clip([0.2, 0.8], *sigma_bounds), 15):
        for t in np.geomspace(*np.clip([0.2, 2.0], *tau_bounds), 15):
            assert _chain_nll(v, dt_k, s, t) >= best - 1e-6


def test_process_bounds_modes():
    from imugraph.calibration.velocity_process import SIGMA_BOUNDS, TAU_BOUNDS, process_bounds

    assert process_bounds("free", 0.5, 2.0) == (SIGMA_BOUNDS, TAU_BOUNDS) == process_bounds("free_hv", 0.5, 2.0)
    (s_lo, s_hi), (t_lo, t_hi) = process_bounds("bounded", 0.5, 2.0)
    assert (s_lo, t_hi) == (0.5, 2.0) and s_hi == SIGMA_BOUNDS[1] and t_lo == TAU_BOUNDS[0]
    assert process_bounds("bounded_hv", np.array([0.5, 0.5, 0.8]), 2.0) == ((s_lo, s_hi), (t_lo, t_hi))
    for bad in ("on", "off", "bounded_xy"):
        with pytest.raises(ValueError, match="estimate_velocity_process"):
            process_bounds(bad, 0.5, 2.0)


def test_horizontal_and_vertical_processes_recovered_separately():
    """Per-axis moments, pooled per group: (x, y) one process, z another."""
    rng = np.random.default_rng(9)
    dt_k = np.full(4000, 0.2)
    v = np.c_[_ar1(rng, dt_k, 0.3, 0.9)[:, :2], _ar1(rng, dt_k, 1.0, 0.3)[:, :1]]
    s0, s1 = moments(v)
    sh, th = fit_gauss_markov(s0[:, :2], s1[:, :2], dt_k)
    sz, tz = fit_gauss_markov(s0[:, 2:], s1[:, 2:], dt_k)
    assert abs(sh / 0.3 - 1) < 0.06 and abs(th / 0.9 - 1) < 0.1
    assert abs(sz / 1.0 - 1) < 0.06 and abs(tz / 0.3 - 1) < 0.1


def test_estimated_process_is_recorded_in_the_calibration_and_used_by_smoothing():
    """calibrate records the estimated σ_v, τ_v in the Calibration (and calibration.json); smooth_fixed with
    that calibration uses them unless told otherwise; bad values in the file fail by name."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.calibration.result import Calibration
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.sim.motion import random_rotation_motion
    from imugraph.sim.sensors import SensorParams, simulate_imu

    rng = np.random.default_rng(8)
    rate = 50.0
    motion = random_rotation_motion(40.0, rate, rng, rest_s=2.0)
    n = len(motion.t)
    ramp = np.clip(np.minimum(motion.t - 2.0, motion.t[-1] - 2.0 - motion.t) / 0.5, 0.0, 1.0)
    v = _ar1(rng, np.full(n - 1, 1 / rate), 0.8, 0.4) * ramp[:, None]
    n_acc = np.vstack([np.diff(v, axis=0) * rate, np.zeros((1, 3))])
    params = SensorParams(gyro_noise=np.full(3, 0.003), acc_noise=np.full(3, 0.03), mag_noise=np.full(3, 0.005))
    s = simulate_imu(motion.t, motion.nRb, motion.b_omega, n_acc, params, rng)
    est = calibrate(s, Options(gyro_map=False, max_outer=4))            # default: "bounded_ar2"
    cal = est.calibration
    assert cal.velocity_sigma == pytest.approx(est.info["velocity_sigma"])
    assert cal.velocity_tau == pytest.approx(est.info["velocity_tau"])
    assert cal.velocity_sigma >= 0.5 - 1e-12 and cal.velocity_tau <= 2.0 + 1e-12   # the bounds
    assert cal.velocity_sigma > 0.55                                # moved: the sensor moves more than 0.5 m/s
    back = Calibration.from_dict(cal.to_dict())
    assert (back.velocity_sigma, back.velocity_tau) == (cal.velocity_sigma, cal.velocity_tau)
    q_default = smooth_fixed(s, cal, max_iterations=10)
    q_given = smooth_fixed(s, cal, velocity_sigma=cal.velocity_sigma, velocity_tau=cal.velocity_tau,
                           max_iterations=10)
    q_start = smooth_fixed(s, cal, velocity_sigma=0.5, velocity_tau=2.0, max_iterations=10)
    np.testing.assert_array_equal(q_default, q_given)
    assert np.max(np.abs(q_default - q_start)) > 1e-9
    assert Calibration.from_dict({**cal.to_dict(), "velocity_sigma": None}).velocity_sigma is None
    with pytest.raises(ValueError, match="positive number"):
        Calibration.from_dict({**cal.to_dict(), "velocity_tau": -1.0})
