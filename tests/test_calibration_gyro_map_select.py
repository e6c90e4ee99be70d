"""The gyro map kept or dropped by a held-out accelerometer test (imugraph.calibration.gyro_map_select)."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from imugraph.calibration import gyro_map_select as gs
from imugraph.calibration.ml import Options, calibrate
from imugraph.io.session import Session
from imugraph.sim.scenario import distorted_session


def _strapdown_session(n=600, rate=100.0, tilt_axis=(0.0, 1.0, 0.0)):
    """A sensor turning at 1 rad/s about a horizontal body axis that starts horizontal... written out here:
    the rotation about the fixed nav axis a, R(t) = Rot(a, t), gravity seen in the body g_b = R(t)ᵀ (0, 0, g)."""
    t = np.arange(n) / rate
    a = np.asarray(tilt_axis, float)
    w = 1.0
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = [np.eye(3) + np.sin(w * ti) * K + (1 - np.cos(w * ti)) * K @ K for ti in t]   # Rodrigues
    acc = np.array([Ri.T @ [0, 0, 9.81] for Ri in R])
    gyr = np.tile(w * a, (n, 1))                    # a body axis that stays the nav axis a
    return Session(t, gyr, acc, np.full((n, 3), np.nan), name="k", source="k.npz")


def test_gravity_carry_known_answer():
    s = _strapdown_session()
    starts, stops = np.array([0, 200]), np.array([200, 400])
    zero = np.zeros((s.n, 3))
    # the true gyro carries gravity exactly: s_b = 0 (up to the strapdown's first-order hold)
    ok = gs.gravity_carry(s, np.zeros((3, 3)), zero, 0.0, 9.81, starts, stops, 0.2, 2.0)
    assert np.all(ok < 1e-8)
    # a 1 % scale error on the turning axis: over a stretch, the windows' centres are 1.8 s apart, so the gyro
    # turns gravity 1.8 rad × 1 % too far: |Δu| = 2 sin(0.018/2) ≈ 0.018
    E = np.diag([0.0, 0.01, 0.0])
    bad = gs.gravity_carry(s, E, zero, 0.0, 9.81, starts, stops, 0.2, 2.0)
    assert np.allclose(np.sqrt(bad), 2 * np.sin(0.018 / 2), rtol=0.02)
    # scale error on an axis the sensor does not turn about: no effect
    assert np.all(gs.gravity_carry(s, np.diag([0.01, 0, 0]), zero, 0.0, 9.81, starts, stops, 0.2, 2.0) < 1e-8)
    # a window with a non-clean sample (|a| far from g) is skipped
    acc = s.acc.copy()
    acc[210] *= 1.5
    out = gs.gravity_carry(replace(s, acc=acc), E, zero, 0.0, 9.81, starts, stops, 0.2, 2.0)
    assert np.isfinite(out[0]) and np.isnan(out[1])


def test_sample_bias_by_segment():
    s = _strapdown_session(n=1000)                   # 10 s at 100 Hz, segments of 5 s
    est = SimpleNamespace(info={"gyro_bias_segments": np.array([[1.0, 0, 0], [2.0, 0, 0]])})
    b = gs.sample_bias(est, s, 5.0)
    assert np.all(b[:500, 0] == 1.0) and np.all(b[500:, 0] == 2.0)


def test_select_off_by_default_and_gates_skip_the_test():
    assert Options().gyro_map_select is False
    s, _ = distorted_session(2, duration_s=30, rate_hz=50)
    est = calibrate(s, Options(gyro_map_select=True, gyro_map_min_turns=1e9))   # coverage gate fails
    assert est.info["gyro_map_select"]["keep"] is False
    assert "gates" in est.info["gyro_map_select"]["reason"]
    assert np.allclose(est.calibration.gyro_map, 0.0)


def test_excluded_intervals_and_uncorrected_samples():
    from imugraph.calibration.gyro_map import GyroMapState, excluded_intervals

    skf = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2, 3])      # 3 intervals, last keyframe alone
    ex = np.zeros(10, bool)
    ex[4] = True
    assert np.array_equal(excluded_intervals(ex, skf, 3), [False, True, False])
    assert excluded_intervals(None, skf, 3) is None
    st = GyroMapState(0.02, exclude=ex)
    st.E = np.diag([0.1, 0.0, 0.0])
    w = np.ones((10, 3))
    out = st.corrected(w)
    assert np.allclose(out[4], 1.0) and np.allclose(out[0], [1.1, 1.0, 1.0])


def _with_gyro_map(session, E):
    """The session's gyro as a sensor with scale/misalignment E would read it: (I + E) b_gyr = ω."""
    return replace(session, gyr=np.linalg.solve(np.eye(3) + E, session.gyr.T).T)


def test_select_keeps_a_real_gyro_map_and_drops_a_spurious_one():
    s, _ = distorted_session(3, duration_s=90, rate_hz=50)
    opt = Options(gyro_map_select=True, gyro_map_min_turns=3.0)      # 23 clean turns in 90 s
    E = np.diag([0.02, -0.015, 0.01])
    est = calibrate(_with_gyro_map(s, E), opt)
    rep = est.info["gyro_map_select"]
    assert rep["keep"] and rep["z"] > 2.0
    assert np.allclose(np.diag(est.calibration.gyro_map), np.diag(E), atol=0.006)
    est0 = calibrate(s, opt)                           # no gyro error: whatever Ê the gates let through is dropped
    assert not est0.info["gyro_map_select"]["keep"]
    assert np.allclose(est0.calibration.gyro_map, 0.0)
