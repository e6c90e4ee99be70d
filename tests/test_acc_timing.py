"""Accelerometer–gyroscope sample timing (imugraph.calibration.acc_timing, Options.acc_lead_samples)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imugraph.calibration.acc_timing import lead_accelerometer, with_lead
from imugraph.calibration.ml import Options, calibrate
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.evaluate import inclination_error
from imugraph.io.session import Session
from imugraph.sim.sensors import SensorParams, simulate_imu


def test_whole_lead_moves_rows_and_holds_the_first():
    a = np.arange(30.0).reshape(10, 3)
    out = lead_accelerometer(a, 2)
    np.testing.assert_array_equal(out[2:], a[:-2])          # row i holds row i − 2
    np.testing.assert_array_equal(out[:2], a[[0, 0]])
    back = lead_accelerometer(a, -3)                          # a lag: row i holds row i + 3
    np.testing.assert_array_equal(back[:-3], a[3:])
    np.testing.assert_array_equal(back[-3:], a[[-1, -1, -1]])


def test_fractional_lead_is_exact_on_a_ramp_and_leaves_the_input():
    i = np.arange(50.0)
    a = np.stack([0.5 * i, -2.0 * i + 1.0, np.full(50, 9.81)], axis=1)
    keep = a.copy()
    out = lead_accelerometer(a, 0.75)
    # independent answer: the ramp evaluated 0.75 rows earlier (linear interpolation is exact on a line)
    j = i[1:] - 0.75
    np.testing.assert_allclose(out[1:], np.stack([0.5 * j, -2.0 * j + 1.0, np.full(49, 9.81)], axis=1),
                               atol=1e-12)
    np.testing.assert_array_equal(a, keep)
    np.testing.assert_array_equal(lead_accelerometer(a, 0.0), a)


def test_fractional_lead_delays_a_sine():
    rate, f0, d = 200.0, 2.0, 0.4
    t = np.arange(400) / rate
    a = np.stack([np.sin(2 * np.pi * f0 * t)] * 3, axis=1)
    out = lead_accelerometer(a, d)
    want = np.sin(2 * np.pi * f0 * (t - d / rate))
    # linear interpolation error ≤ (Δt)² max|a''| / 8
    assert np.max(np.abs(out[1:, 0] - want[1:])) < (2 * np.pi * f0 / rate) ** 2 / 8 + 1e-12


@pytest.mark.parametrize("lead", [0.4, 1.4, -0.6])
def test_fractional_lead_with_the_gyro_turns_gravity_back_exactly(lead):
    """Constant body rate: the body-fixed view of gravity a_b(t) = Exp(ω t)ᵀ R0ᵀ g e_z is known in closed
    form; rows sensed δ samples ahead are returned to their own time exactly (no noise averaging)."""
    rate, n = 100.0, 60
    dt = np.full(n, 1.0 / rate)
    w = np.array([0.3, -2.0, 0.7])
    R0 = Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix()

    def a_b(t):
        return np.einsum("nji,j->ni", Rotation.from_rotvec(np.outer(t, w)).as_matrix(), R0.T @ [0, 0, 9.81])

    t = np.arange(n) / rate
    sensed = a_b(t + lead / rate)                     # row j read the force at the time of row j + δ
    out = lead_accelerometer(sensed, lead, np.tile(w, (n, 1)), dt)
    inner = slice(2, n - 2)
    np.testing.assert_allclose(out[inner], a_b(t)[inner], atol=1e-10)
    assert np.max(np.abs(sensed[inner] - a_b(t)[inner])) > 1e-3      # the lead was visible


@pytest.mark.parametrize("bad", [np.full((5, 2), 1.0), np.ones(6)])
def test_bad_shape_names_the_field(bad):
    with pytest.raises(SessionError, match="acc"):
        lead_accelerometer(bad, 1.0, source="x.npz")


@pytest.mark.parametrize("lead", [np.nan, 40.0])
def test_bad_lead_names_the_option(lead):
    with pytest.raises(SessionError, match="acc_lead_samples"):
        lead_accelerometer(np.zeros((20, 3)), lead, source="x.npz")


def _spin(lead: int, seed: int = 0, rate: float = 100.0, T: float = 30.0) -> Session:
    """A sensor spun at 6 rad/s about a horizontal nav axis (with slow wobble about the others), rests at the
    ends and in the middle; the accelerometer's row i reads the specific force of row i + lead."""
    rng = np.random.default_rng(seed)
    n = int(T * rate)
    t = np.arange(n) / rate
    env = np.clip((t - 3.0), 0, 1) * np.clip((T - 3.0 - t), 0, 1) * np.clip(np.abs(t - T / 2) / 1.5 - 1.0, 0, 1)
    n_w = np.stack([1.0 * np.sin(0.9 * t), np.full(n, 6.0), 1.2 * np.cos(0.6 * t)], 1) * env[:, None]
    R = np.empty((n, 3, 3))
    R[0] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    steps = Rotation.from_rotvec(n_w / rate).as_matrix()
    for k in range(n - 1):                 # R_{k+1} = Exp(n_ω_k Δt) R_k = R_k Exp(b_ω_k Δt), b_ω = Rᵀ n_ω
        R[k + 1] = steps[k] @ R[k]
    b_w = np.einsum("nji,nj->ni", R, n_w)
    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    p = SensorParams(gyro_noise=np.full(3, 0.005), acc_noise=np.full(3, 0.05), mag_noise=np.full(3, 0.01),
                     mag_D=np.diag([1.1, 0.9, 1.0]), mag_o=np.array([0.2, -0.1, 0.3]))
    s = simulate_imu(t, q, b_w, np.zeros((n, 3)), p, rng)
    if lead:
        acc = np.roll(s.acc, -lead, axis=0)
        acc[-lead:] = s.acc[-1]
        s = Session(s.t, s.gyr, acc, s.mag, s.quat, s.movement, s.source, s.name, dict(s.meta))
    return s


def _incl(s: Session, lead: float) -> float:
    est = calibrate(s, Options(acc_lead_samples=lead), allow_weak=True)
    return inclination_error(est.quat, s.quat, s.movement, s.rate).rms_deg


def test_matching_lead_removes_the_tilt_of_a_spinning_sensor():
    """A one-sample accelerometer lead on a sensor spinning about a horizontal axis tilts the smoother
    (eq. 2 of acc_timing); pairing the rows as they were sensed removes it."""
    s = _spin(lead=1)
    wrong, right = _incl(s, 0.0), _incl(s, 1.0)
    assert right < 0.2
    assert wrong > 3 * right


def test_lead_on_correctly_timed_data_costs_accuracy():
    s = _spin(lead=0)
    right, wrong = _incl(s, 0.0), _incl(s, 1.0)
    assert right < 0.2
    assert wrong > 3 * right


def test_with_lead_zero_is_the_same_session():
    s = _spin(lead=0, T=8.0)
    assert with_lead(s, 0.0) is s
    moved = with_lead(s, 1.0)
    np.testing.assert_array_equal(moved.acc[1:], s.acc[:-1])
    np.testing.assert_array_equal(moved.gyr, s.gyr)
    half = with_lead(s, 0.5)                           # rotation only: the norm of every row is kept
    np.testing.assert_allclose(np.linalg.norm(half.acc, axis=1), np.linalg.norm(s.acc, axis=1), rtol=1e-12)
    with pytest.raises(SessionError, match="gyr"):
        lead_accelerometer(s.acc, 0.5, s.gyr[:-1], s.dt, source=s.source)


def test_fixed_calibration_smoother_retimes_the_accelerometer():
    from imugraph.graphs.cpp_smoother import smooth_fixed

    s = _spin(lead=1, T=12.0)
    cal = calibrate(s, Options(acc_lead_samples=1.0, max_outer=2), allow_weak=True).calibration
    assert cal.acc_lead_samples == 1.0                 # recorded in the calibration (calibration.json)
    q_opt = smooth_fixed(s, cal, acc_lead_samples=1.0, max_iterations=20)
    q_pre = smooth_fixed(with_lead(s, 1.0), cal, acc_lead_samples=0.0, max_iterations=20)
    np.testing.assert_allclose(q_opt, q_pre, atol=1e-12)
    q_cal = smooth_fixed(s, cal, max_iterations=20)    # default: the calibration's δ
    np.testing.assert_allclose(q_cal, q_opt, atol=1e-12)
    assert Calibration.from_dict(cal.to_dict()).acc_lead_samples == 1.0
