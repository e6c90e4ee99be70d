"""The stream applies the calibration's gyro scale/misalignment E as the batch path does: ω = (I + E)·b_gyr − b
(imugraph.calibration.gyro_map; `smooth --calibration` via Calibration.corrected_gyro)."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.evaluate import orientation_error
from imugraph.graphs.cpp_smoother import smooth_fixed
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_run import stream_session
from imugraph.io.session import Session
from imugraph.sim.scenario import distorted_session

RATE = 100.0
FIXED = StreamOptions(online_calibration=False, field_sigma=None)
# a gyro 3 % slow about z, 1 % fast about x, 0.5° misalignment x↔y: the sensor reports b_gyr = (I + E)⁻¹ ω
E = np.array([[0.01, 0.0087, 0.0], [-0.0087, 0.0, 0.0], [0.0, 0.0, -0.03]]) * -1.0


@pytest.fixture(scope="module")
def case():
    session, truth = distorted_session(3, 20.0, RATE)
    raw = np.linalg.solve(np.eye(3) + E, session.gyr.T).T          # what a sensor with (I + E) reports
    scaled = Session(session.t, raw, session.acc, session.mag, session.quat, session.movement,
                     session.source, session.name, session.meta)
    cal = truth.to_calibration()
    return session, scaled, cal, replace(cal, gyro_map=E.copy())


def _push_all(cal, s, opt):
    sm = StreamSmoother(cal, RATE, opt, g0=9.81)
    return np.array([sm.push(s.t[i], s.gyr[i], s.acc[i], s.mag[i]) for i in range(s.n)])


def test_push_applies_i_plus_e(case):
    """Known answer: streaming the raw gyro with E in the calibration equals streaming (I + E)·b_gyr (formed
    here by numpy) with E = 0, sample by sample."""
    _, scaled, cal, cal_e = case
    part = scaled.slice(0, 600)
    pre = Session(part.t, part.gyr @ (np.eye(3) + E).T, part.acc, part.mag, part.quat, part.movement,
                  part.source, part.name, part.meta)
    opt = StreamOptions(lag_s=1.0, online_calibration=False)
    q_e = _push_all(cal_e, part, opt)
    q_0 = _push_all(cal, pre, opt)
    assert np.allclose(q_e, q_0, atol=1e-10)


def test_gyro_map_one_model_two_solvers(case):
    """With E, iSAM2's smoothed output equals `smooth_fixed` with the same calibration (which applies E through
    Calibration.corrected_gyro) to < 0.1° RMS, and applying E beats ignoring it against the truth."""
    session, scaled, cal, cal_e = case
    batch = smooth_fixed(scaled, cal_e, rotation_tol_deg=0.001)
    r = stream_session(scaled, cal_e, FIXED)
    gap = orientation_error(r.smoothed, batch, None, RATE, heading=False, max_shift=0.0).rms_deg
    assert gap < 0.1
    err_e = orientation_error(r.filtered, session.quat, None, RATE).rms_deg
    err_0 = orientation_error(stream_session(scaled, cal, FIXED).filtered, session.quat, None, RATE).rms_deg
    assert err_e < err_0
