"""calibration.json carries the magnetometer rows the calibration's solve left out (disturbance windows'
`left_out` runs, Options.window_trial_verdict), and its readers (`smooth --calibration` through
Calibration.corrected, the stream likewise) leave out the same rows: calibrate → write → read → corrected
equals what the calibrate path's final solve saw (disturbance.apply_windows)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from imugraph.calibration.disturbance import Window, apply_windows, left_out_runs
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.io.writers import read_calibration_json, write_calibration_json


def _irregular_t(n: int, seed: int = 0) -> np.ndarray:
    """Times with irregular steps (not multiples of a round number): a float round trip must be exact."""
    return 12.345 + np.cumsum(np.random.default_rng(seed).uniform(0.003, 0.004, n))


def test_left_out_runs_are_runs_of_consecutive_rows():
    t = np.arange(20) * 0.5
    assert left_out_runs(t, np.array([9, 3, 4, 5, 12, 13])) == [[1.5, 2.5], [4.5, 4.5], [6.0, 6.5]]
    assert left_out_runs(t, None) == [] and left_out_runs(t, np.array([], int)) == []


def test_as_dict_exports_left_out_rows_of_a_modelled_window_only():
    t = np.arange(20) * 0.5
    modelled = Window(2, 10, np.array([1.0, 0.0, 0.0]), True, drop=np.array([2, 3, 9]))
    assert modelled.as_dict(t)["left_out"] == [[1.0, 1.5], [4.5, 4.5]]
    unmodelled = Window(12, 18, np.array([1.0, 0.0, 0.0]), False, drop=np.array([12]))
    d = unmodelled.as_dict(t)
    assert d["left_out"] == [] and d["modelled"] is False        # left out whole by modelled = false


def test_round_trip_leaves_out_the_rows_the_solve_left_out(tmp_path):
    n = 600
    t = _irregular_t(n)
    y = np.random.default_rng(1).normal(size=(n, 3))
    wins = [Window(50, 200, np.array([0.3, -0.2, 1.1]), True, drop=np.r_[50:60, 120, 190:200]),
            Window(300, 400, None, False),
            Window(450, 550, np.array([-0.5, 0.0, 0.2]), True)]        # modelled, nothing dropped
    y_solve, w_solve = apply_windows(wins, y)
    path = write_calibration_json(tmp_path / "calibration.json",
                                  Calibration(D=np.eye(3), o=np.zeros(3), dip_deg=60.0,
                                              disturbances=[w.as_dict(t) for w in wins]))
    out = read_calibration_json(path).corrected(t, y)
    left_out = np.any(np.isnan(out), axis=1)
    assert np.array_equal(left_out, w_solve == 0)                 # the same rows, by index
    assert left_out.sum() == 10 + 1 + 10 + 100
    np.testing.assert_array_equal(out[~left_out], y_solve[~left_out])


def test_files_without_left_out_read_as_before(tmp_path):
    t = np.arange(0, 10, 0.1)
    doc = Calibration(D=np.eye(3), o=np.zeros(3), dip_deg=60.0).to_dict()
    doc["disturbances"] = [{"t_start": 2.0, "t_end": 3.0, "offset": [0.5, 0.0, -0.5], "modelled": True}]
    (tmp_path / "c.json").write_text(json.dumps(doc))
    out = read_calibration_json(tmp_path / "c.json").corrected(t, np.ones((len(t), 3)))
    assert np.all(np.isfinite(out))                              # no row left out of a modelled window
    inside = (t >= 2.0) & (t <= 3.0)
    np.testing.assert_allclose(out[inside], [[0.5, 1.0, 1.5]] * inside.sum())


@pytest.mark.parametrize("bad", [[[3.0]], [[3.0, 2.0]], [[1.0, None]], "x", [[1.0, 2.0, 3.0]]])
def test_malformed_left_out_is_a_clear_error(tmp_path, bad):
    doc = Calibration(D=np.eye(3), o=np.zeros(3), dip_deg=60.0).to_dict()
    doc["disturbances"] = [{"t_start": 2.0, "t_end": 3.0, "offset": [0.5, 0.0, -0.5], "modelled": True,
                            "left_out": bad}]
    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(SessionError) as exc:
        read_calibration_json(path)
    msg = str(exc.value)
    assert str(path) in msg and "disturbances[0].left_out" in msg and "expected" in msg


def test_calibrate_write_read_smooth_sees_the_solve_rows(tmp_path, monkeypatch):
    """End to end on a simulated magnet attached for 30 s (3 × the field's offset larger than the field, as BROAD
    32): with window_trial_verdict the window is modelled and its padded margins (no magnet yet: the offset
    does not explain them) are left out; the file read back leaves out exactly the rows of calibrate's final
    solve, and smooth_fixed from the file equals smooth_fixed from the in-memory calibration."""
    import imugraph.calibration.ml as ml
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.sim.scenario import distorted_session

    seen = []
    real = ml.apply_windows

    def spy(windows, b_mag):
        out = real(windows, b_mag)
        seen.append(out[1].copy())
        return out

    monkeypatch.setattr(ml, "apply_windows", spy)
    s, truth = distorted_session(11, duration_s=90.0, rate_hz=100.0)
    mag = s.mag.copy()
    mag[(s.t > 30.0) & (s.t < 60.0)] += np.array([0.3, -0.2, 1.1]) * truth.field_norm
    s = s.with_mag(mag)
    est = ml.calibrate(s, ml.Options(window_trial_verdict=True))
    wins = est.calibration.disturbances
    assert len(wins) == 1 and wins[0]["modelled"] and wins[0]["left_out"]      # margins left out
    weights = seen[-1]                       # the final solve's magnetometer weights (after the last round)
    cal = read_calibration_json(write_calibration_json(tmp_path / "calibration.json", est.calibration))
    out = cal.corrected(s.t, s.mag)
    no_sample = np.any(np.isnan(replace(cal, disturbances=[]).corrected(s.t, s.mag)), axis=1)   # the lag's edge
    assert np.array_equal(np.any(np.isnan(out), axis=1), (weights == 0) | no_sample)
    assert 0 < (weights == 0).sum() < 0.2 * 30.0 * 100.0           # the margins, not the window
    q_file, q_mem = smooth_fixed(s, cal), smooth_fixed(s, est.calibration)
    np.testing.assert_array_equal(q_file, q_mem)


def test_smooth_fixed_through_long_left_out_stretches():
    """Rows left out (NaN after Calibration.corrected) for 8 s of every 14 s between 20 and 100 s of a simulated
    rotating session (37 % of the rows), the true calibration held fixed: the smoothed orientation stays near the
    one without gaps (0.117° RMS; gyro-only heading across 8 s adds little) instead of leaving the basin (51° when
    smooth_fixed's start pulled a keyframe without a field sample toward the nearest keyframe's field, in that
    keyframe's body frame: orientation_init.complementary_keyframes(borrow_field=False) since session 15)."""
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.evaluate import orientation_error
    from imugraph.sim.scenario import distorted_session

    s, tr = distorted_session(0, duration_s=120.0, rate_hz=100.0)
    mag = s.mag.copy()
    for a in range(20, 100, 14):
        mag[(s.t >= a) & (s.t < a + 8)] = np.nan
    cal = Calibration(D=tr.D, o=tr.o, dip_deg=float(np.rad2deg(tr.dip_rad)), gyro_bias=tr.gyro_bias,
                      noise={k: np.asarray(v, float) for k, v in tr.noise.items()})
    err = orientation_error(smooth_fixed(s.with_mag(mag), cal), s.quat, s.movement.astype(bool), s.rate).rms_deg
    assert err < 0.5
