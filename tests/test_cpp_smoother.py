"""The C++-only fixed-calibration smoother (imugraph.graphs.cpp_smoother, cpp_velocity): its factors against
the batch path's velocity model, and linear acceleration modelled as motion against the noise treatment on
simulated translation and on a BROAD trial."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.evaluate import orientation_error
from imugraph.factors.velocity import velocity_model
from imugraph.geometry import expmap, quat_to_rotmat
from imugraph.graphs.cpp_smoother import smooth_fixed
from imugraph.graphs.cpp_velocity import (gauss_markov_factors, imu_bias_key, initial_motion, pose_key,
                                          super_sample_pim, super_samples)
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu

G = 9.81


def _imu_case(rng, params, R_next, v_next=None):
    """An ImuFactor from one super-sample, and Values at R_k (random), R_{k+1} = R_next(R_k, ΔR)."""
    R_k, dR = expmap(rng.normal(size=3)), expmap(rng.normal(scale=0.3, size=3))
    dv, dt, b_gyr = rng.normal(size=3), 0.1, rng.normal(scale=0.01, size=3)
    omega, acc = super_samples(dR[None], dv[None], np.array([dt]), b_gyr[None])
    pim = super_sample_pim(params, omega[0], acc[0], dt, b_gyr)
    f = gtsam.ImuFactor(pose_key(0), keys.vel(0), pose_key(1), keys.vel(1), imu_bias_key(0), pim)
    v_k = rng.normal(scale=0.7, size=3)
    c = np.array([0.0, 0.0, -G]) * dt + R_k @ dv                  # v_{k+1} − v_k of the model
    v = np.stack([v_k, v_k + c if v_next is None else v_next])
    p_next = v_k * dt + 0.5 * c * dt                               # initial_motion's position step
    vals = gtsam.Values()
    vals.insert(pose_key(0), gtsam.Pose3(gtsam.Rot3(R_k), np.zeros(3)))
    vals.insert(pose_key(1), gtsam.Pose3(gtsam.Rot3(R_next(R_k, dR)), p_next))
    vals.insert(keys.vel(0), v[0])
    vals.insert(keys.vel(1), v[1])
    vals.insert(imu_bias_key(0), gtsam.imuBias.ConstantBias(np.zeros(3), b_gyr))
    return f.unwhitenedError(vals), R_k, dR, dv, dt, v


def test_super_sample_imu_factor_is_the_velocity_model():
    """The ImuFactor built from one super-sample holds the gyro residual −Log(ΔRᵀ R_kᵀ R_{k+1}) and the batch
    path's velocity residual e_k = v_{k+1} − v_k − n_grav Δt − R_k Δv_k (as −(R_k ΔR)ᵀ e_k, same norm), and
    initial_motion's positions zero its position rows."""
    rng = np.random.default_rng(5)
    params = gtsam.PreintegrationParams.MakeSharedU(G)
    for _ in range(5):
        delta = rng.normal(scale=0.05, size=3)
        err, R_k, dR, _, _, _ = _imu_case(rng, params, lambda R, dR: R @ dR @ expmap(delta))
        np.testing.assert_allclose(err[:3], -delta, atol=1e-9)
        np.testing.assert_allclose(err[3:], 0.0, atol=1e-9)
        err, R_k, dR, dv, dt, v = _imu_case(rng, params, lambda R, dR: R @ dR, rng.normal(size=3))
        e, _ = velocity_model(np.stack([R_k, R_k @ dR]), v, dv[None], np.array([dt]), G)
        np.testing.assert_allclose(err[6:], -(R_k @ dR).T @ e[0], atol=1e-9)
        np.testing.assert_allclose(err[:3], 0.0, atol=1e-9)


def test_gauss_markov_factors_are_the_prior_density():
    """−log density of v_0 ~ N(0, σ_v²), v_{k+1} − φ_k v_k ~ N(0, σ_v²(1 − φ_k²)), φ_k = exp(−Δt_k/τ_v)."""
    rng = np.random.default_rng(6)
    K, sigma_v, tau_v = 7, 0.5, 2.0
    dt = rng.uniform(0.05, 0.2, K - 1)
    v = rng.normal(size=(K, 3))
    graph = gtsam.NonlinearFactorGraph()
    for f in gauss_markov_factors(dt, sigma_v, tau_v):
        graph.add(f)
    vals = gtsam.Values()
    for k in range(K):
        vals.insert(keys.vel(k), v[k])
    phi = np.exp(-dt / tau_v)
    var_w = sigma_v**2 * (1.0 - phi**2)
    expected = 0.5 * (v[0] @ v[0] / sigma_v**2 + np.sum(np.sum((v[1:] - phi[:, None] * v[:-1]) ** 2, 1) / var_w))
    assert graph.error(vals) == pytest.approx(expected, rel=1e-10)


def test_initial_motion_minimises_the_linear_velocity_cost():
    rng = np.random.default_rng(7)
    K, sigma_v, tau_v = 30, 0.5, 2.0
    nRk = expmap(rng.normal(size=(K, 3)))
    dv, dt = rng.normal(size=(K - 1, 3)), np.full(K - 1, 0.1)
    sig_dv = rng.uniform(0.01, 0.05, K - 1)
    v, p = initial_motion(nRk, dv, sig_dv, dt, G, sigma_v, tau_v)

    def cost(v):
        e, _ = velocity_model(nRk, v, dv, dt, G)
        phi = np.exp(-dt / tau_v)
        w = (v[1:] - phi[:, None] * v[:-1]) / (sigma_v * np.sqrt(1 - phi**2))[:, None]
        return np.sum((e / sig_dv[:, None]) ** 2) + np.sum(w**2) + np.sum((v[0] / sigma_v) ** 2)

    c0 = cost(v)
    for _ in range(20):
        assert cost(v + 1e-3 * rng.normal(size=v.shape)) > c0
    c = np.array([0.0, 0.0, -G]) * dt[:, None] + np.einsum("kij,kj->ki", nRk[:-1], dv)
    np.testing.assert_allclose(np.diff(p, axis=0), v[:-1] * dt[:, None] + 0.5 * c * dt[:, None], atol=1e-12)


def _simulated(seed: int, translation_m: float):
    rng = np.random.default_rng(seed)
    motion = random_rotation_motion(60.0, 100.0, rng, rms_rate=0.8, translation_m=translation_m, pauses=2)
    prm = SensorParams(gyro_bias=np.array([0.01, -0.005, 0.008]), gyro_noise=np.full(3, 0.005),
                       acc_noise=np.full(3, 0.05), mag_noise=np.full(3, 0.5), field_norm=50.0,
                       dip_rad=np.deg2rad(65.0), g=G)
    s = simulate_imu(motion.t, motion.nRb, motion.b_omega, motion.n_acc, prm, rng)
    cal = Calibration(D=prm.D_unit, o=prm.mag_o, dip_deg=float(np.rad2deg(prm.dip_rad)), gyro_bias=prm.gyro_bias,
                      noise={"gyr": prm.gyro_noise, "acc": prm.acc_noise, "mag": prm.mag_noise})
    return s, cal, motion


def _rms_deg(q, q_ref):
    """RMS rotation angle to the truth (the simulated nav frame is the smoother's: no alignment)."""
    R, R_ref = quat_to_rotmat(q), quat_to_rotmat(q_ref)
    c = np.clip((np.einsum("nij,nij->n", R, R_ref) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.rad2deg(np.sqrt(np.mean(np.arccos(c) ** 2))))


@pytest.mark.parametrize("seed", [1, 2])
def test_translation_is_motion_not_noise(seed):
    """With |linear acceleration| ≈ 0.5 g RMS, modelling it as motion must beat treating it as noise
    (a keyframe's mean specific force then tilts the estimate toward it) by a wide margin, and be about as
    accurate as on the same rotations without translation."""
    s, cal, motion = _simulated(seed, translation_m=0.3)
    assert np.sqrt(np.mean(np.sum(motion.n_acc**2, axis=1))) > 0.3 * G        # the premise: fast translation
    err_velocity = _rms_deg(smooth_fixed(s, cal), s.quat)
    err_noise = _rms_deg(smooth_fixed(s, cal, linear_acceleration="noise"), s.quat)
    assert err_velocity < 0.5 * err_noise
    s0, cal0, _ = _simulated(seed, translation_m=0.0)
    err_still = _rms_deg(smooth_fixed(s0, cal0), s0.quat)
    assert err_velocity < 2.0 * err_still


def test_fixed_gravity_and_estimated_gravity_agree_on_simulation():
    s, cal, _ = _simulated(3, translation_m=0.3)
    q_est = smooth_fixed(s, cal)
    q_fix = smooth_fixed(s, cal, g=G)
    assert _rms_deg(q_est, q_fix) < 0.1


def test_unknown_treatment_is_a_one_line_error():
    s, cal, _ = _simulated(1, translation_m=0.0)
    with pytest.raises(SessionError) as info:
        smooth_fixed(s.slice(0, 500), cal, linear_acceleration="bogus")
    assert "linear_acceleration" in str(info.value) and "\n" not in str(info.value)


def test_broad_fast_combined_trial_close_to_the_batch_path(data_dir):
    """BROAD 21 (fast rotation and translation) with the calibration estimated by the batch path:
    the C++ smoother must be within 0.5° RMS of the batch path's own orientation (the two solve the same
    model; 0.5° is the spread between offline VQF and the batch path on BROAD's undisturbed trials), and
    beat the linear-acceleration-as-noise smoother."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.io.readers import load_session

    path = data_dir / "broad" / "21_undisturbed_fast_combined.mat"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    s = load_session(path)
    est = calibrate(s, Options(), allow_weak=True)
    mask = s.movement.astype(bool)
    err_batch = orientation_error(est.quat, s.quat, mask, s.rate).rms_deg
    err_cpp = orientation_error(smooth_fixed(s, est.calibration), s.quat, mask, s.rate).rms_deg
    err_noise = orientation_error(smooth_fixed(s, est.calibration, linear_acceleration="noise"), s.quat, mask,
                                  s.rate).rms_deg
    assert err_cpp <= err_batch + 0.5
    assert err_cpp < err_noise


def test_smooth_fixed_applies_the_gyro_map():
    """A gyro read through (I + E)⁻¹ (2 % scale, 1 % misalignment): with the calibration's E the smoother
    sees exactly the original rates (ω = (I + E)·b_gyr − b), so it returns the undistorted run's orientation;
    without E it is worse."""
    s, cal, _ = _simulated(4, translation_m=0.0)
    E = np.array([[0.02, 0.01, 0.0], [-0.01, -0.015, 0.005], [0.0, 0.01, 0.02]])
    scaled = replace(s, gyr=s.gyr @ np.linalg.inv(np.eye(3) + E).T)
    cal_e = replace(cal, gyro_map=E)
    q_ref = smooth_fixed(s, cal)
    q_with = smooth_fixed(scaled, cal_e)
    q_without = smooth_fixed(scaled, cal)
    assert _rms_deg(q_with, q_ref) < 1e-3
    assert _rms_deg(q_with, s.quat) < _rms_deg(q_without, s.quat) - 0.05
