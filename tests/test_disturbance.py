"""Lasting magnetic disturbances: windows found from the calibrated norm, a body-fixed offset per window
recovered, and the calibration and orientation kept (imugraph.calibration.disturbance)."""

import numpy as np
import pytest

from imugraph.calibration.disturbance import Window, apply_windows, detect_windows
from imugraph.calibration.ml import Options, calibrate
from imugraph.evaluate import orientation_error
from imugraph.sim.scenario import distorted_session


def _calibrated_field(seed: int, norm_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """60 s at 100 Hz of random unit-field directions whose norm scatters by norm_noise (relative)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 60, 0.01)
    m = rng.normal(size=(len(t), 3))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    return t, m * (1 + norm_noise * rng.normal(size=(len(t), 1)))


def test_detect_windows_finds_a_step_in_the_norm():
    t, m = _calibrated_field(1, 0.01)
    m[2000:3500] *= 1.4                                   # 20 s–35 s: 40 % off the sphere
    wins = detect_windows(t, m)
    assert len(wins) == 1
    assert abs(t[wins[0].start] - 20.0) < 1.0 and abs(t[wins[0].stop - 1] - 35.0) < 1.0


def test_undisturbed_field_has_no_window():
    t, m = _calibrated_field(2, 0.02)
    assert detect_windows(t, m) == []


def test_apply_windows_removes_offsets_and_drops_unexplained():
    y = np.zeros((10, 3))
    wins = [Window(2, 4, np.array([1.0, 2.0, 3.0]), True), Window(6, 8, None, False)]
    out, w = apply_windows(wins, y)
    np.testing.assert_allclose(out[2:4], -np.array([[1.0, 2.0, 3.0]] * 2))
    assert w.tolist() == [1, 1, 1, 1, 1, 1, 0, 0, 1, 1]
    assert np.all(y == 0)                                 # the input is untouched


def test_apply_windows_leaves_out_the_dropped_rows_of_a_modelled_window():
    y = np.zeros((10, 3))
    out, w = apply_windows([Window(2, 6, np.array([1.0, 0.0, 0.0]), True, drop=np.array([2, 5]))], y)
    assert w.tolist() == [1, 1, 0, 1, 1, 0, 1, 1, 1, 1]
    np.testing.assert_allclose(out[2:6, 0], -1.0)
    _, w = apply_windows([Window(2, 6, None, False, drop=np.array([2]))], y)     # left out: the whole window
    assert w.tolist() == [1, 1, 0, 0, 0, 0, 1, 1, 1, 1]


@pytest.mark.parametrize("opts", [{}, {"window_trial_verdict": True}])
def test_attached_magnet_window_is_modelled(opts):
    s, truth = distorted_session(11, duration_s=90.0, rate_hz=100.0)
    offset = np.array([0.3, -0.2, 1.1]) * truth.field_norm       # larger than the field, as in BROAD 32
    window = (s.t > 30.0) & (s.t < 60.0)
    mag = s.mag.copy()
    mag[window] += offset
    est = calibrate(s.with_mag(mag), Options(**opts))
    if opts:        # judged on a solve with it modelled, once: modelled from the trial round on, rounds converge
        assert est.calibration.converged and est.calibration.iterations < Options().max_outer
        assert all(h["windows"][0]["modelled"] for h in est.info["history"])
    wins = est.info["disturbance_windows"]
    assert len(wins) == 1 and wins[0]["modelled"]
    assert abs(wins[0]["t_start"] - 30.0) < 1.5 and abs(wins[0]["t_end"] - 60.0) < 1.5
    np.testing.assert_allclose(wins[0]["offset"], offset, atol=0.05 * truth.field_norm)
    cal = est.calibration
    assert np.linalg.norm(cal.o - truth.o) < 0.05 * truth.field_norm
    err = orientation_error(est.quat, s.quat, s.movement.astype(bool), s.rate).rms_deg
    assert err < 2.0


def test_calibration_carries_windows_to_a_known_calibration_smoother():
    from imugraph.calibration.result import Calibration

    t = np.arange(0, 10, 0.1)
    y = np.ones((len(t), 3))
    cal = Calibration(D=np.eye(3), o=np.zeros(3), dip_deg=60.0, disturbances=[
        {"t_start": 2.0, "t_end": 3.0, "offset": [0.5, 0.0, -0.5], "modelled": True},
        {"t_start": 6.0, "t_end": 7.0, "offset": None, "modelled": False}])
    back = Calibration.from_dict(cal.to_dict())            # through calibration.json
    out = back.corrected(t, y)
    inside = (t >= 2.0) & (t <= 3.0)
    np.testing.assert_allclose(out[inside], [[0.5, 1.0, 1.5]] * inside.sum())
    assert np.all(np.isnan(out[(t >= 6.0) & (t <= 7.0)]))
    np.testing.assert_allclose(out[t < 1.9], 1.0)
    assert np.all(y == 1.0)                                # the input is untouched
