"""Online calibration of a stream (imugraph.graphs.stream_calib + StreamSmoother): the closed-form refit
against the truth, and the streamed calibration converging from a perturbed start."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.geometry import quat_to_rotmat
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_calib import OnlineMagCalibration
from imugraph.sim.scenario import distorted_session


def _z(cal, truth_cal, std):
    """(D, o) errors in units of their reported std."""
    return np.r_[((cal.D - truth_cal.D) / std["D"]).ravel(), (cal.o - truth_cal.o) / std["o"]]


def test_refit_with_true_orientations_is_the_truth():
    """Known answer: with the true orientations, the closed-form refit of (1)–(2) from running sums recovers
    the simulated D, o and dip within 3 of its reported std, whatever the start (here 5 % and 5° off), and
    folding the samples in chunks gives the same sums as all at once."""
    session, truth = distorted_session(3, 30.0, 100.0)
    cal = truth.to_calibration()
    scale = np.cbrt(abs(np.linalg.det(cal.D)))
    rng = np.random.default_rng(1)
    start = replace(cal, D=cal.D + 0.05 * scale * rng.standard_normal((3, 3)), o=cal.o + 0.05 * scale, dip_deg=cal.dip_deg + 5)
    R = quat_to_rotmat(session.quat)
    whole, chunks = OnlineMagCalibration(start, gate=1.0), OnlineMagCalibration(start, gate=1.0)
    whole.add(session.mag, R)
    for i in range(0, session.n, 37):
        chunks.add(session.mag[i:i + 37], R[i:i + 37])
    assert np.allclose(whole.Suy, chunks.Suy) and np.isclose(whole.n, chunks.n)
    est = whole.refit(30.0)
    assert np.all(np.abs(_z(est, cal, est.std)) < 3.0)
    assert abs(est.dip_deg - cal.dip_deg) < 3.0 * est.std["dip_deg"] + 1e-3
    assert np.max(est.std["D"]) < 0.01 * scale                 # and the std is informative
    assert len(whole.history) == 1 and whole.history[0]["std"] is not None


def test_refit_before_data_keeps_the_start():
    cal = distorted_session(3, 12.0, 50.0)[1].to_calibration()
    oc = OnlineMagCalibration(cal)
    assert oc.refit(0.0) is cal and oc.history[0]["std"] is None
    assert oc.add(np.full((4, 3), np.nan), np.tile(np.eye(3), (4, 1, 1))) == 0


def test_final_graph_reissues_every_magnetometer_factor():
    """iSAM2 mode: the recorded factor indices are the magnetometer factors, and the end-of-stream graph
    holds the same number of factors with those rebuilt on the final calibration."""
    import gtsam

    session, truth = distorted_session(3, 12.0, 50.0)
    cal = truth.to_calibration()
    sm = StreamSmoother(cal, 50.0, StreamOptions(calib_every_s=2.0))
    for i in range(session.n):
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    factors = sm._solver.getFactorsUnsafe()
    assert all(isinstance(factors.at(i), gtsam.MagPoseFactorPose3) for i in sm._mag_index.values())
    assert sm.stats.calib_refits >= 4 and len(sm.calibration_history) == sm.stats.calib_refits
    assert sm._final_graph().size() == factors.size()


def test_streamed_calibration_converges_to_the_truth():
    """From a start 1 % off in every entry of D and o (the dip held at the truth, the default), 90 s of
    streaming with 10 s memory brings D and o within 3 reported std of the simulated truth, and much closer
    than the start (the refit feeds better magnetometer factors, which give better orientations)."""
    session, truth = distorted_session(3, 90.0, 50.0)
    cal = truth.to_calibration()
    scale = np.cbrt(abs(np.linalg.det(cal.D)))
    rng = np.random.default_rng(0)
    start = replace(cal, D=cal.D + 0.01 * scale * rng.standard_normal((3, 3)), o=cal.o + 0.01 * scale * rng.standard_normal(3))
    sm = StreamSmoother(start, 50.0, StreamOptions(calib_every_s=2.0, calib_memory_s=10.0),
                        g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
    for i in range(session.n):
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    sm.finish()
    est = sm.cal
    assert sm.stats.failed_updates == 0
    assert np.all(np.abs(_z(est, cal, est.std)) < 3.0)
    err0 = np.abs(np.r_[(start.D - cal.D).ravel(), start.o - cal.o]).max()
    assert np.abs(np.r_[(est.D - cal.D).ravel(), est.o - cal.o]).max() < 0.25 * err0
    t = [row["t"] for row in sm.calibration_history]
    assert np.all(np.diff(t) > 0) and t[-1] > 85.0
