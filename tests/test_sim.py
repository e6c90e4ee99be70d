"""Tests of the single-IMU simulator: motion, sensor models, distortions, the demo scenario."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.errors import ImugraphError
from imugraph.geometry import integrate_gyro, quat_conj, quat_mul, quat_to_rotmat, quat_to_rotvec
from imugraph.sim.distortion import apply_distortion, distort_session, random_distortion
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.scenario import distorted_session
from imugraph.sim.sensors import SensorParams, simulate_imu

RATE = 100.0


def _angle(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """(N,) rotation angle between two quaternion arrays, rad."""
    return np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(q_a), q_b)), axis=1)


@pytest.fixture(scope="module")
def motion():
    return random_rotation_motion(60.0, RATE, np.random.default_rng(7), rest_s=2.0, pauses=1)


def test_zero_noise_gyro_reproduces_orientation(motion):
    t, nRb, b_omega, n_acc = motion
    s = simulate_imu(t, nRb, b_omega, n_acc, SensorParams(), np.random.default_rng(0))
    q_int = integrate_gyro(s.gyr, np.full(t.shape[0], 1.0 / RATE), s.quat[0])
    assert np.max(_angle(q_int, nRb)) < 1e-6
    # Each step separately: Log(q_k⁻¹ q_{k+1}) = ω_k Δt (ω constant over [t_k, t_{k+1})).
    step = quat_to_rotvec(quat_mul(quat_conj(nRb[:-1]), nRb[1:]))
    np.testing.assert_allclose(step, b_omega[:-1] / RATE, atol=1e-12)


def test_motion_rests_rates_and_coverage(motion):
    t, nRb, b_omega, n_acc = motion
    assert t.shape == (6000,) and nRb.shape == (6000, 4)
    np.testing.assert_allclose(np.diff(t), 1.0 / RATE)
    rest = (t <= 2.0) | (t >= t[-1] - 2.0)
    assert np.all(b_omega[rest] == 0.0) and np.all(n_acc == 0.0)
    assert np.ptp(nRb[t <= 2.0], axis=0).max() == 0.0           # orientation constant at rest
    assert np.linalg.norm(b_omega, axis=1).max() < 4.0            # default max_rate
    assert np.sqrt(np.mean(b_omega[~rest] ** 2)) > 0.3            # it really moves
    # The body "up" axis visits every octant of the sphere (rotation about all three axes).
    b_up = quat_to_rotmat(nRb)[:, 2, :]
    octant = (b_up > 0) @ np.array([1, 2, 4])
    assert set(np.unique(octant)) == set(range(8))


def test_translation_is_zero_at_rest():
    m = random_rotation_motion(20.0, RATE, np.random.default_rng(3), translation_m=0.1)
    rest = (m.t <= 2.0) | (m.t >= m.t[-1] - 2.0)
    assert np.all(m.n_acc[rest] == 0.0)
    assert np.sqrt(np.mean(m.n_acc[~rest] ** 2)) > 0.1


def test_accelerometer_at_rest_reads_plus_g_up(motion):
    t, nRb, b_omega, n_acc = motion
    s = simulate_imu(t, nRb, b_omega, n_acc, SensorParams(g=9.81), np.random.default_rng(0))
    rest = t <= 2.0
    np.testing.assert_allclose(np.linalg.norm(s.acc[rest], axis=1), 9.81, rtol=1e-12)
    b_up = np.einsum("nji,j->ni", quat_to_rotmat(nRb), np.array([0.0, 0.0, 1.0]))   # bRn·[0,0,1]
    np.testing.assert_allclose(s.acc / 9.81, b_up, atol=1e-12)


def test_magnetometer_model(motion):
    t, nRb, b_omega, n_acc = motion
    dip = np.deg2rad(55.0)
    D = np.array([[1.2, 0.05, -0.02], [0.0, 0.9, 0.03], [0.01, -0.04, 1.1]])
    o = np.array([10.0, -20.0, 5.0])
    p = SensorParams(mag_D=D, mag_o=o, dip_rad=dip, field_norm=50.0)
    s = simulate_imu(t, nRb, b_omega, n_acc, p, np.random.default_rng(0))
    m_cal = np.linalg.solve(50.0 * D, (s.mag - o).T).T                # the paper's D = F·D
    np.testing.assert_allclose(np.linalg.norm(m_cal, axis=1), 1.0, atol=1e-12)
    up = s.acc / np.linalg.norm(s.acc, axis=1, keepdims=True)
    # n_mag · n_up = −sin δ: the field makes 90° + δ with "up".
    np.testing.assert_allclose(np.sum(m_cal * up, axis=1), -np.sin(dip), atol=1e-12)
    # Independent check of the direction: nRb · m_cal = [cos δ, 0, −sin δ].
    n_field = np.einsum("nij,nj->ni", quat_to_rotmat(nRb), m_cal)
    np.testing.assert_allclose(n_field, np.tile([np.cos(dip), 0.0, -np.sin(dip)], (t.size, 1)), atol=1e-12)


def test_noise_bias_and_subrate(motion):
    t, nRb, b_omega, n_acc = motion
    p = SensorParams(gyro_bias=[0.01, -0.02, 0.03], gyro_noise=0.02, acc_noise=[0.1, 0.2, 0.3],
                     mag_noise=0.5, field_norm=50.0, mag_every=4)
    s = simulate_imu(t, nRb, b_omega, n_acc, p, np.random.default_rng(1))
    gyr_err = s.gyr - b_omega
    np.testing.assert_allclose(gyr_err.mean(0), [0.01, -0.02, 0.03], atol=4 * 0.02 / np.sqrt(t.size))
    np.testing.assert_allclose(gyr_err.std(0), 0.02, rtol=0.05)
    clean = simulate_imu(t, nRb, b_omega, n_acc, SensorParams(g=9.81), np.random.default_rng(1)).acc
    np.testing.assert_allclose((s.acc - clean).std(0), [0.1, 0.2, 0.3], rtol=0.05)
    valid = np.all(np.isfinite(s.mag), axis=1)
    assert np.array_equal(valid, np.arange(t.size) % 4 == 0)
    assert np.all(np.isnan(s.mag[~valid]))
    assert s.meta["sensor_params"]["mag_every"] == 4


def test_invalid_params_raise_named_errors():
    with pytest.raises(ImugraphError, match="gyro_noise"):
        SensorParams(gyro_noise=[0.1, 0.1])
    with pytest.raises(ImugraphError, match="mag_D"):
        SensorParams(mag_D=np.zeros((3, 3)))
    with pytest.raises(ImugraphError, match="mag_every"):
        SensorParams(mag_every=0)
    with pytest.raises(ImugraphError, match="rest_s"):
        random_rotation_motion(3.0, RATE, np.random.default_rng(0), rest_s=2.0)
    t = np.arange(5) / RATE
    with pytest.raises(ImugraphError, match="nRb"):
        simulate_imu(t, np.ones((4, 4)), np.zeros((5, 3)), np.zeros((5, 3)), SensorParams(),
                     np.random.default_rng(0))


def _decompose(A: np.ndarray):
    """Scales, skew angles (deg) and misalignment angle (deg) of A = S·K·Mᵀ (module doc of distortion)."""
    s = np.linalg.norm(A, axis=1)
    U = A / s[:, None]
    a = np.arcsin(U[0] @ U[1])
    b = np.arcsin(U[0] @ U[2])
    c = np.arcsin((U[1] @ U[2] - np.sin(a) * np.sin(b)) / (np.cos(a) * np.cos(b)))
    K = np.array([[1, 0, 0], [np.sin(a), np.cos(a), 0],
                  [np.sin(b), np.cos(b) * np.sin(c), np.cos(b) * np.cos(c)]])
    Mt = np.linalg.solve(K, U)
    return s, np.rad2deg([a, b, c]), Mt


def test_random_distortion_ranges():
    field_norm = 48.0
    for seed in range(200):
        A, b = random_distortion(np.random.default_rng(seed), field_norm)
        s, skew_deg, Mt = _decompose(A)
        assert np.all((s >= 0.75) & (s <= 1.3))
        assert np.all(np.abs(skew_deg) <= 6.0 + 1e-9)
        np.testing.assert_allclose(Mt @ Mt.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(Mt) > 0
        mis_deg = np.rad2deg(np.arccos(np.clip((np.trace(Mt) - 1) / 2, -1, 1)))
        assert mis_deg <= 6.0 + 1e-6
        assert np.all(np.abs(b) <= 1.2 * field_norm)
    # Not degenerate: over 200 draws the ranges are actually used.
    draws = [random_distortion(np.random.default_rng(k), 1.0) for k in range(200)]
    scales = np.concatenate([np.linalg.norm(A, axis=1) for A, _ in draws])
    offsets = np.concatenate([b for _, b in draws])
    assert scales.min() < 0.8 and scales.max() > 1.25 and np.abs(offsets).max() > 1.1


def test_apply_and_distort_session_keep_input():
    session, truth = distorted_session(5, duration_s=10.0)
    mag = session.mag.copy()
    mag[3] = np.nan
    session = session.with_mag(mag)
    before = {k: getattr(session, k).copy() for k in ("t", "gyr", "acc", "mag", "quat")}
    meta_before = dict(session.meta)
    A = np.array([[1.1, 0.1, 0.0], [0.0, 0.9, -0.05], [0.02, 0.0, 1.2]])
    b = np.array([3.0, -4.0, 5.0])
    out = distort_session(session, A, b)
    for key, value in before.items():
        assert np.array_equal(getattr(session, key), value, equal_nan=True)
    assert session.meta == meta_before and "distortion" in out.meta
    assert np.all(np.isnan(out.mag[3]))
    k = 10
    np.testing.assert_allclose(out.mag[k], A @ session.mag[k] + b, rtol=1e-12)
    assert np.all(np.isnan(apply_distortion(np.full((2, 3), np.nan), A, b)))
    # Eq. (1): the distorted magnetometer follows D' = A D, o' = A o + b (up to the 1 % noise).
    m_cal = np.linalg.solve(A @ truth.D, (out.mag - (A @ truth.o + b)).T).T
    norms = np.linalg.norm(m_cal[np.isfinite(m_cal[:, 0])], axis=1)
    assert abs(np.median(norms) - 1.0) < 0.01


def test_scenario_truth_and_reproducibility():
    s1, tr1 = distorted_session(11, duration_s=30.0, rate_hz=50.0)
    s2, tr2 = distorted_session(11, duration_s=30.0, rate_hz=50.0)
    s3, _ = distorted_session(12, duration_s=30.0, rate_hz=50.0)
    assert s1.n == 1500 and abs(s1.rate - 50.0) < 1e-9
    for key in ("t", "gyr", "acc", "mag", "quat"):
        assert np.array_equal(getattr(s1, key), getattr(s2, key))
    assert np.array_equal(tr1.D, tr2.D) and not np.array_equal(s1.mag, s3.mag)
    assert 40.0 <= tr1.dip_deg <= 75.0
    assert np.all((np.abs(np.rad2deg(tr1.gyro_bias)) >= 0.3) & (np.abs(np.rad2deg(tr1.gyro_bias)) <= 0.7))
    # Truth explains the data: calibrated norm 1 within the 1 % magnetometer noise.
    m_cal = tr1.to_calibration().apply(s1.mag)
    assert abs(np.median(np.linalg.norm(m_cal, axis=1)) - 1.0) < 0.01
    # Gyro at the initial rest reads the bias plus 0.01 rad/s noise.
    rest = s1.t <= 1.9
    np.testing.assert_allclose(s1.gyr[rest].mean(0), tr1.gyro_bias, atol=4 * 0.01 / np.sqrt(rest.sum()))
    # The distortion is far from identity (a calibration has something to do).
    assert np.abs(tr1.D / tr1.field_norm - np.eye(3)).max() > 0.03 or np.abs(tr1.o).max() > 5.0
