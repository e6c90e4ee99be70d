"""StreamOptions.velocity_end (session 18, helper V): the stream's end-of-stream EM of the velocity process σ_v, τ_v
(imugraph.graphs.stream_velocity). Known answers: the process factors against the batch's residuals
(factors.velocity.ar2_residuals, cpp_velocity.gauss_markov_factors), EM on a simulated linear chain recovering the
simulated process, and a simulated stream whose velocity follows a known Gauss–Markov process while its start
calibration says τ_v = 0.05 s."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.calibration.result import Calibration
from imugraph.calibration.velocity_process import process_bounds
from imugraph.factors.velocity import ar2_residuals, ar2_stationary
from imugraph.graphs.cpp_velocity import gauss_markov_factors
from imugraph.graphs.stream_velocity import (VelocityEnd, _with, chain_information, change, e_step, m_step,
                                             process_bands, process_chain, process_factors)
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu
from sim_processes import gauss_markov_path

BOUNDS = process_bounds("bounded", 0.5, 2.0)      # the batch's: σ_v ≥ 0.5 m/s, τ_v ≤ 2 s
from stream_runs import stream_isolated as _stream, truth_rms as _truth_rms


def _dense(bands: np.ndarray) -> np.ndarray:
    """Symmetric matrix from lower banded form (b+1, K)."""
    K = bands.shape[1]
    M = np.zeros((K, K))
    for i in range(bands.shape[0]):
        idx = np.arange(K - i)
        M[idx + i, idx] = M[idx, idx + i] = bands[i, :K - i]
    return M


def _information(factors: list, K: int, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(K, K) information on one nav axis and the gradient vector of ½Σ|r|² at x = 0 from linear factors."""
    g = gtsam.NonlinearFactorGraph()
    for f in factors:
        g.add(f)
    x = gtsam.Values()
    for k in range(K):
        x.insert(keys.vel(k), np.zeros(3))
    H = np.zeros((3 * K, 3 * K))
    for i in range(g.size()):
        lf = g.at(i).linearize(x)
        ks = list(g.at(i).keys())
        A = lf.augmentedInformation()[:-1, :-1]
        cols = np.concatenate([3 * gtsam.Symbol(k).index() + np.arange(3) for k in ks])
        H[np.ix_(cols, cols)] += A
    return H[axis::3, axis::3], H


@pytest.mark.parametrize("proc", [("gm", 0.7, 0.4), ("ar2", 1.2, -0.45, 0.03), ("ar2", 1.2, -0.45, 0.03, 2)])
def test_process_bands_equal_the_factors(proc):
    """Eq. (1)/(3)'s banded precision = the information of the factors put into the graph (no cross-axis terms)."""
    K, dt_k = 11, np.full(10, 0.1)
    H1, H = _information(process_factors(proc, dt_k), K)
    assert np.allclose(H1, _dense(process_bands(proc, dt_k, K)), rtol=1e-10, atol=1e-10)
    assert np.allclose(H, np.kron(H1, np.eye(3)))


def test_gm_factors_are_the_streams():
    """The first-order factors are exactly cpp_velocity.gauss_markov_factors (what _start and _close issue)."""
    K, dt_k = 7, np.array([0.1, 0.1, 0.12, 0.1, 0.08, 0.1])
    H1, _ = _information(gauss_markov_factors(dt_k, 0.6, 0.9), K)
    assert np.allclose(H1, _dense(process_bands(("gm", 0.6, 0.9), dt_k, K)), rtol=1e-12, atol=1e-12)


def test_ar2_factors_match_the_batch_residuals_and_numerical_derivative():
    """The AR(2) factors' cost is ½|ar2_residuals(v)|² (the batch's, factors.velocity) at random v, and their
    linearised gradient equals the numerical derivative of the graph error."""
    a1, a2, q = 1.1, -0.35, 0.02
    K = 8
    rng = np.random.default_rng(1)
    v = rng.standard_normal((K, 3))
    g = gtsam.NonlinearFactorGraph()
    for f in process_factors(("ar2", a1, a2, q), np.full(K - 1, 0.1)):
        g.add(f)
    x = gtsam.Values()
    for k in range(K):
        x.insert(keys.vel(k), v[k])
    assert np.isclose(g.error(x), 0.5 * np.sum(ar2_residuals(v, a1, a2, q) ** 2), rtol=1e-12)
    gfg = g.linearize(x)
    grad = gfg.gradientAtZero()              # Aᵀ(A·0 − b) = −Aᵀb: the gradient of the error at x
    eps = 1e-6
    for k in (0, 3, K - 1):
        for j in range(3):
            xp, xm = gtsam.Values(x), gtsam.Values(x)
            d = np.zeros(3)
            d[j] = eps
            xp.update(keys.vel(k), v[k] + d)
            xm.update(keys.vel(k), v[k] - d)
            num = (g.error(xp) - g.error(xm)) / (2 * eps)
            assert np.isclose(grad.at(keys.vel(k))[j], num, rtol=1e-6, atol=1e-6)


def test_chain_information_of_known_factors():
    """chain_information of the process factors themselves at a random x: Λ_R = their bands, η = −Λ x."""
    K, dt_k = 10, np.full(9, 0.1)
    fs = gauss_markov_factors(dt_k, 0.8, 0.5)
    g = gtsam.NonlinearFactorGraph()
    for f in fs:
        g.add(f)
    rng = np.random.default_rng(2)
    v = rng.standard_normal((K, 3))
    x = gtsam.Values()
    for k in range(K):
        x.insert(keys.vel(k), v[k])
    ab, eta, cross = chain_information(g, list(range(g.size())), x, K)
    L = _dense(process_bands(("gm", 0.8, 0.5), dt_k, K)[:2])
    for i in range(3):
        assert np.allclose(_dense(ab[:, :, i]), L)
        assert np.allclose(eta[:, i], -L @ v[:, i])
    assert cross < 1e-12


def _em(mode, v_true, dt, sigma_dv, rng, start, iters=200, spacing=1):
    """EM (e_step, m_step) on a linear chain: increments c_k = v_{k+1} − v_k + N(0, σ_dv²), linearised at 0."""
    K = len(v_true)
    c = np.diff(v_true, axis=0) + sigma_dv * rng.standard_normal((K - 1, 3))
    a = 1.0 / sigma_dv**2
    ab = np.zeros((2, K, 3))
    ab[0, :-1] += a
    ab[0, 1:] += a
    ab[1, :-1] = -a
    eta = np.zeros((K, 3))
    eta[:-1] -= a * c
    eta[1:] += a * c
    dt_k, proc = np.full(K - 1, dt), start
    for _ in range(iters):
        bands = 2 * spacing + 1 if spacing > 1 else 3
        new = m_step(mode, *e_step(ab, eta, np.zeros((K, 3)), process_bands(proc, dt_k, K), bands), dt_k, BOUNDS,
                     spacing)
        done = new[0] == proc[0] and change(proc, new) < 1e-6
        proc = new
        if done:
            break
    return new


def test_em_recovers_a_first_order_process():
    """A simulated Gauss–Markov velocity (σ_v 0.8 m/s, τ_v 0.6 s, 4000 keyframes at 10 Hz) seen through noisy
    increments: EM from the start (0.5, 0.05) returns the simulated process within 6 %."""
    rng = np.random.default_rng(3)
    K, dt, sigma, tau = 4000, 0.1, 0.8, 0.6
    v = gauss_markov_path(rng, K, dt, sigma, tau)
    _, s_hat, t_hat = _em("gm", v, dt, 0.05, rng, ("gm", 0.5, 0.05))
    assert abs(s_hat / sigma - 1) < 0.06 and abs(t_hat / tau - 1) < 0.06, (s_hat, t_hat)


def test_em_recovers_an_ar2_process():
    """A simulated AR(2) velocity (a_1 1.2, a_2 −0.5, q 0.08: an oscillation) through noisy increments: the AR(2)
    EM (the batch's fit_ar2) from the first-order start recovers a_1, a_2 within 0.05 and q within 10 %."""
    rng = np.random.default_rng(4)
    K, a1, a2, q = 4000, 1.2, -0.5, 0.08
    assert ar2_stationary(a1, a2, q)[0] > 0.25          # √γ_0 above the bounded mode's 0.5 m/s
    v = np.zeros((K, 3))
    for k in range(1, K - 1):
        v[k + 1] = a1 * v[k] + a2 * v[k - 1] + np.sqrt(q) * rng.standard_normal(3)
    _, a1_hat, a2_hat, q_hat = _em("ar2", v, 0.1, 0.03, rng, ("gm", 0.5, 2.0))
    assert abs(a1_hat - a1) < 0.05 and abs(a2_hat - a2) < 0.05 and abs(q_hat / q - 1) < 0.1, (a1_hat, a2_hat, q_hat)


def test_em_at_the_batch_spacing_recovers_a_first_order_process():
    """"ar2_batch" (eq. 4: the AR(2) at 2 keyframe intervals, first-order equivalent) on a simulated Gauss–Markov
    velocity (σ_v 0.7 m/s, τ_v 0.4 s at 10 Hz): √γ_0 and −2Δt/ln ρ_1 recover the simulated process within 8 %."""
    rng = np.random.default_rng(5)
    K, dt, sigma, tau = 6000, 0.1, 0.7, 0.4
    v = gauss_markov_path(rng, K, dt, sigma, tau)
    kind, s_hat, t_hat = _em("ar2", v, dt, 0.05, rng, ("gm", 0.5, 2.0), spacing=2)
    assert kind == "gm" and abs(s_hat / sigma - 1) < 0.08 and abs(t_hat / tau - 1) < 0.08, (s_hat, t_hat)


def test_spaced_terms_at_spacing_one_are_the_batch_terms():
    """Eq. (4)'s pooled sums at s = 1 equal velocity_ar2.ar2_objective_terms of the same moments."""
    from imugraph.calibration.velocity_ar2 import ar2_objective_terms, lag_moments
    from imugraph.graphs.stream_velocity import _spaced_terms

    rng = np.random.default_rng(6)
    m, Z = rng.standard_normal((50, 3)), rng.random((3, 50, 3))
    for a, b in zip(_spaced_terms(m, Z, 1), ar2_objective_terms(lag_moments(m, Z))):
        assert np.allclose(a, b)


def test_unknown_mode_raises():
    with pytest.raises(ValueError):
        VelocityEnd(None, "ar3")


# ------------------------------------------------------------------ a simulated stream
SIGMA_V, TAU_V = 0.6, 1.5          # the simulated velocity process


def _session(seed: int, rate: float = 50.0, kf_hz: float = 10.0, duration: float = 60.0):
    """Random rotations (sim.motion) with a nav velocity that follows the Gauss–Markov process (SIGMA_V, TAU_V) at the
    stream's keyframes (constant acceleration inside each keyframe interval); the true magnetometer calibration."""
    rng = np.random.default_rng(seed)
    t, nRb, b_omega, _ = random_rotation_motion(duration, rate, rng, rest_s=2.0)
    stride = int(round(rate / kf_hz))
    n, dt = len(t), stride / rate
    K = (n - 1) // stride + 2
    v = gauss_markov_path(rng, K, dt, SIGMA_V, TAU_V)
    n_acc = np.repeat(np.diff(v, axis=0) / dt, stride, axis=0)[:n]
    noise = {"gyr": np.full(3, 0.01), "acc": np.full(3, 0.05), "mag": np.full(3, 0.5)}
    p = SensorParams(gyro_bias=np.deg2rad([0.4, -0.5, 0.3]), gyro_noise=noise["gyr"], acc_noise=noise["acc"],
                     dip_rad=np.deg2rad(60.0), field_norm=50.0, mag_noise=noise["mag"])
    s = simulate_imu(t, nRb, b_omega, n_acc, p, rng, name="gm_velocity")
    cal = Calibration(D=50.0 * np.eye(3), o=np.zeros(3), dip_deg=60.0, gyro_bias=p.gyro_bias.copy(), noise=noise,
                      converged=True)
    return s, cal


@pytest.fixture(scope="module")
def runs():
    """Seed 0: the start calibration's process (0.5 m/s, 0.05 s: nearly white) off and with velocity_end="ar2_batch"."""
    s, cal = _session(0)
    start = replace(cal, velocity_sigma=0.5, velocity_tau=0.05)
    return s, _stream(s, start), _stream(s, start, velocity_end="ar2_batch")


def test_stream_estimate_moves_to_the_truth(runs):
    """τ̂_v from 0.05 s to within a factor 1.6 of the simulated 1.5 s; σ̂_v within 15 % of 0.6 m/s."""
    _, _, (on, _) = runs
    r = on.velocity_end_result
    assert r["tau_start"] == 0.05 and abs(np.log(r["tau"] / TAU_V)) < np.log(1.6), r
    assert abs(r["sigma"] / SIGMA_V - 1) < 0.15, r
    assert (on.cal.velocity_sigma, on.cal.velocity_tau) == (r["sigma"], r["tau"])   # calibration.json carries them
    assert runs[1][0].cal.velocity_tau == 0.05                                       # off: the start's


def test_stream_smoothed_output_improves_filtered_unchanged(runs):
    """Smoothed vs truth better than with the start's process (measured 0.70 → 0.32°; the simulated process fed:
    0.29°); the filtered output identical."""
    s, (off, q_off), (on, q_on) = runs
    assert np.array_equal(q_off, q_on)
    e_off, e_on = _truth_rms(off.smoothed(), s), _truth_rms(on.smoothed(), s)
    assert e_on < 0.7 * e_off, (e_on, e_off)


def test_end_graph_process_replaced_not_duplicated(runs):
    """The end graph holds exactly K process factors (v_0's prior + K−1 steps), and rebuilding them with the start's
    process (Δt_k from the keyframe times) reproduces the graph's error: replaced, not added."""
    s, (off, _), _ = runs
    K = off._k + 1
    graph = off._final_graph()
    idx, other = process_chain(graph, K)
    assert len(idx) == K and other
    base = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        if graph.exists(i) and i not in set(idx):
            base.add(graph.at(i))
    dt_k = np.diff(np.asarray(off._kf_t))[:K - 1]
    rebuilt = _with(base, process_factors(("gm", off._sig_v, off._tau_v), dt_k))
    assert rebuilt.size() == graph.size()
    assert np.isclose(rebuilt.error(off._final), graph.error(off._final), rtol=1e-12)


def test_unidentified_process_keeps_the_start():
    """"ar2_batch_id" on a simulation without translation (true velocity 0: the data hold no innovation variance above
    the bounded mode's floor): not identified, the end graph keeps the start calibration's (σ_v, τ_v) and the smoothed
    output equals the option off's (the fit is floor-bound: q̂ = q_floor)."""
    from imugraph.sim.scenario import distorted_session

    s, truth = distorted_session(3, 40.0, 50.0)
    cal = truth.to_calibration()
    off, _ = _stream(s, cal)
    guard, _ = _stream(s, cal, velocity_end="ar2_batch_id")
    r = guard.velocity_end_result
    assert not r["identified"] and r["fit"]["f_over_n"] < r["fit"]["q_floor"]
    assert np.isclose(r["fit"]["ar2"][2], r["fit"]["q_floor"])
    assert (r["sigma"], r["tau"]) == (r["sigma_start"], r["tau_start"])
    # the same graph; the end LM starts from the extension's solve instead of iSAM2's estimate (measured: 3e-5°)
    assert _truth_rms(guard.smoothed(), s) == pytest.approx(_truth_rms(off.smoothed(), s), abs=1e-3)


def test_simulated_process_is_identified(runs):
    """The Gauss–Markov simulation (σ_v 0.6 m/s) holds innovation variance above the floor: identified."""
    s, (off, _), _ = runs
    cal = replace(off._cal0, velocity_sigma=0.5, velocity_tau=0.05)
    on, _ = _stream(s, cal, velocity_end="ar2_batch_id")
    r = on.velocity_end_result
    assert r["identified"] and abs(np.log(r["tau"] / TAU_V)) < np.log(1.6), r
