"""Tests of imugraph/calibration/gyro_gsens.py: the window relation (2) against the exact rotation, recovery of a
known g-sensitivity G on a simulation, the pooled consistency statistic, bad input, and one real BROAD trial."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imugraph.calibration.gyro_gsens import (G0, fit_gyro_errors, pooled, predicted_rotation, regressors, strapdown,
                                             usable_windows, window_design, window_residual)
from imugraph.config import broad_dir
from imugraph.errors import SessionError
from imugraph.io.session import Session
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu

RATE = 100.0
DEG = np.pi / 180
G_TRUE = np.array([[0.4, -0.3, 0.2], [0.1, 0.5, -0.6], [-0.2, 0.3, 0.3]]) * DEG      # rad/s per g
S_TRUE = np.array([[3e-3, 1e-3, 0.0], [-1e-3, -2e-3, 5e-4], [0.0, 1e-3, 4e-3]])
B_TRUE = np.array([0.2, -0.1, 0.15]) * DEG


def simulated(G: np.ndarray, seed: int = 3, ref_noise_deg: float = 0.1, duration_s: float = 120.0) -> Session:
    """A session whose gyro obeys (1) with bias B_TRUE, scale S_TRUE and g-sensitivity G (specific force from the
    noise-free accelerometer), and whose quat is the truth with ref_noise_deg white rotation noise per axis."""
    rng = np.random.default_rng(seed)
    t, nRb, w, n_acc = random_rotation_motion(duration_s, RATE, rng, translation_m=0.3, rms_rate=1.5)
    s = simulate_imu(t, nRb, w, n_acc, SensorParams(), rng)
    f = s.acc / G0
    # ω_meas = ω + b + G f + S ω_meas  ⇒  ω_meas = (I − S)⁻¹ (ω + b + G f)
    gyr = np.linalg.solve(np.eye(3) - S_TRUE, (w + B_TRUE + f @ G.T).T).T
    noise = Rotation.from_rotvec(rng.standard_normal((len(t), 3)) * ref_noise_deg * DEG)
    q = (Rotation.from_quat(np.c_[nRb[:, 1:], nRb[:, :1]]) * noise).as_quat()
    return Session(t=s.t, gyr=gyr, acc=s.acc, mag=s.mag, quat=np.c_[q[:, 3:], q[:, :3]], movement=s.movement,
                   source="<simulation>", name="gsens")


def test_window_relation_matches_exact_rotation():
    """Eq. (2) (first order) against the exact Log(ΔR_gᵀΔR_o) with a noise-free reference."""
    s = simulated(G_TRUE, ref_noise_deg=0.0, duration_s=40.0)
    X, names = regressors(s.t, s.gyr, s.acc, "base", bias_seg_s=1e3)
    theta = np.r_[B_TRUE, S_TRUE.ravel(), G_TRUE.ravel()]
    assert names[:3] == ["b0_x", "b0_y", "b0_z"] and names[3] == "S_xx" and names[-1] == "G_zz"
    R = strapdown(s.gyr, s.dt)
    a, e = usable_windows(s.movement, np.ones(s.n, bool), int(RATE))
    exact = window_residual(R, s.quat, a, e, 0.0)
    linear = window_design(R, X, s.dt, a, e) @ theta
    assert np.max(np.abs(exact)) > 0.2 * DEG                       # the errors are not trivially small
    assert np.max(np.abs(linear - exact)) < 0.02 * np.max(np.abs(exact))


def test_recovers_known_g_sensitivity():
    s = simulated(G_TRUE)
    fit = fit_gyro_errors(s, s.quat, win_s=1.0)
    G, se = fit.block("G")
    assert fit.lag == 0.0
    assert np.all(np.abs(G - G_TRUE) < 4 * se)
    assert np.max(se) < 0.1 * DEG                                   # determined to < 0.1 °/s/g
    S, se_s = fit.block("S")
    assert np.all(np.abs(S - S_TRUE) < 4 * se_s + 1e-4)
    assert fit.wald("G")[1] < 1e-6
    # the noise-free reference's residual is what (2) cannot explain: 0.1° noise at both ends ≈ 0.14° per axis
    assert 0.1 * DEG < fit.sigma < 0.2 * DEG


def test_no_g_sensitivity_is_not_significant():
    s = simulated(np.zeros((3, 3)), seed=5)
    fit = fit_gyro_errors(s, s.quat, win_s=1.0)
    G, se = fit.block("G")
    assert fit.wald("G")[1] > 1e-3
    assert np.all(np.abs(G) < 4 * se)


def test_split_terms_agree_for_a_physical_g_sensitivity():
    """A sensor cannot tell gravity from acceleration: the gravity and linear parts of G come out equal."""
    s = simulated(G_TRUE, seed=7)
    fit = fit_gyro_errors(s, s.quat, win_s=1.0, terms="split")
    Gg, seg = fit.block("Ggrav")
    Gl, sel = fit.block("Glin")
    assert np.all(np.abs(Gg - G_TRUE) < 4 * seg)
    assert np.all(np.abs(Gl - G_TRUE) < 4 * sel)


def test_pooled_known_answer():
    mean, se, Q = pooled(np.array([1.0, 3.0]), np.array([1.0, 1.0]))
    assert mean == pytest.approx(2.0) and se == pytest.approx(1 / np.sqrt(2)) and Q == pytest.approx(2.0)
    mean, se, Q = pooled(np.array([[1.0], [1.0], [1.0]]), np.array([[1.0], [2.0], [0.5]]))
    assert mean[0] == pytest.approx(1.0) and Q[0] == pytest.approx(0.0)


def test_predicted_rotation_of_a_constant_rate_error():
    """A constant body rate error c while the body turns about the same axis accumulates |c|·T over T."""
    n = 3000
    t = np.arange(n) / RATE
    gyr = np.tile([0.0, 0.0, 1.0], (n, 1))
    s = Session(t=t, gyr=gyr, acc=np.tile([0, 0, G0], (n, 1)), mag=np.full((n, 3), np.nan),
                quat=np.tile([1.0, 0, 0, 0], (n, 1)), movement=np.ones(n, bool), source="<test>", name="c")
    c = 1e-3 * np.eye(3)
    assert predicted_rotation(s, gyr, c, 10.0) == pytest.approx(1e-3 * 10.0, rel=1e-6)


def test_bad_reference_shape():
    s = simulated(G_TRUE, duration_s=20.0)
    with pytest.raises(SessionError, match="quat_ref"):
        fit_gyro_errors(s, s.quat[:-1])
    with pytest.raises(SessionError, match="movement"):
        fit_gyro_errors(s, s.quat, mask=np.zeros(s.n, bool))


@pytest.mark.skipif(not (broad_dir() / "16_undisturbed_fast_translation_B.mat").is_file(), reason="BROAD absent")
def test_broad16_first_minute():
    """Real data: the optical clock lag (≈ 1.25 samples; −1.75 in this module's convention, measured on every
    trial) and a sub-percent gyro scale come out of the first 60 s of BROAD 16."""
    from benchmarks.common import load_broad_trial

    s = load_broad_trial(broad_dir() / "16_undisturbed_fast_translation_B.mat")
    s = s.slice(0, int(60 * s.rate))
    fit = fit_gyro_errors(s, s.quat, win_s=1.0)
    assert -2.5 <= fit.lag <= -1.0
    S, _ = fit.block("S")
    assert np.all(np.abs(np.diag(S)) < 0.01)
    assert fit.sigma < 0.5 * DEG
