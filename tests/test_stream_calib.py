"""Online calibration of a stream by the closed-form refit (imugraph.graphs.stream_calib + StreamSmoother,
`StreamOptions(calib_states=False)`): the refit against the truth, and the streamed calibration converging from
a perturbed start. θ as a graph state (the default): tests/test_stream_calstate.py."""

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


@pytest.mark.parametrize("field", [None, (0.015, 0.003, 0.015)])
def test_final_graph_reissues_every_magnetometer_factor(field):
    """iSAM2 mode: the recorded factor indices are the magnetometer factors (MagPoseFactorPose3; with the field
    perturbation its linearised form on the keyframe's pose and d_k), and the end-of-stream graph holds the same
    number of factors with those rebuilt on the final calibration (with the field: the exact CustomFactor)."""
    import gtsam

    from imugraph.graphs.cpp_velocity import pose_key
    from imugraph.graphs.stream_field import field_key

    session, truth = distorted_session(3, 12.0, 50.0)
    cal = truth.to_calibration()
    sm = StreamSmoother(cal, 50.0, StreamOptions(calib_every_s=2.0, field_sigma=field, calib_states=False))
    for i in range(session.n):
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    factors = sm._solver.getFactorsUnsafe()
    for k, i in sm._mag_index.items():
        f = factors.at(i)
        if field is None:
            assert isinstance(f, gtsam.MagPoseFactorPose3)
        else:
            assert isinstance(f, gtsam.LinearContainerFactor) and set(f.keys()) == {pose_key(k), field_key(k)}
    assert sm.stats.calib_refits >= 4 and len(sm.calibration_history) == sm.stats.calib_refits
    final = sm._final_graph()
    assert final.size() == factors.size()
    if field is not None:
        assert sum(isinstance(final.at(i), gtsam.CustomFactor) for i in range(final.size())) == len(sm._mag_index)


def test_streamed_calibration_converges_to_the_truth():
    """From a start 1 % off in every entry of D and o (the dip held at the truth, the default), 90 s of
    streaming with 10 s memory brings D and o within 3 reported std of the simulated truth, and much closer
    than the start (the refit feeds better magnetometer factors, which give better orientations)."""
    session, truth = distorted_session(3, 90.0, 50.0)
    cal = truth.to_calibration()
    scale = np.cbrt(abs(np.linalg.det(cal.D)))
    rng = np.random.default_rng(0)
    start = replace(cal, D=cal.D + 0.01 * scale * rng.standard_normal((3, 3)), o=cal.o + 0.01 * scale * rng.standard_normal(3))
    sm = StreamSmoother(start, 50.0, StreamOptions(calib_every_s=2.0, calib_memory_s=10.0, calib_states=False),
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


@pytest.mark.parametrize("correlated", [False, True])
def test_whiteness_factor_known_answer(correlated):
    """Eq. (3) on synthetic residuals: white noise gives F ≈ 1; noise held constant over each 100-sample block
    (fully correlated within a block) gives F ≈ 100 = the block length, and the reported std is √F times the
    white-noise std (the calibration's own correlation factor is 1 here)."""
    session, truth = distorted_session(3, 60.0, 100.0)
    cal = replace(truth.to_calibration(), coverage={})
    R = quat_to_rotmat(session.quat)
    y_clean = np.einsum("ij,nkj,k->ni", cal.D, R, cal.n_mag) + cal.o           # D bRn n + o  (bRn = nRbᵀ)
    rng = np.random.default_rng(5)
    oc = OnlineMagCalibration(cal, gate=10.0)
    blocks = 0
    for start in range(0, session.n - 100, 100):
        noise = np.tile(rng.normal(0, 0.3, 3), (100, 1)) if correlated else rng.normal(0, 0.3, (100, 3))
        oc.add(y_clean[start:start + 100] + noise, R[start:start + 100])
        oc.end_block()
        blocks += 1
    est = oc.refit(60.0)
    F = oc.last_whiteness
    assert blocks >= 50 and F is not None
    if correlated:
        assert np.all((F > 60) & (F < 140))
    else:
        assert np.all((F > 0.6) & (F < 1.6))
    ratio = np.asarray(est.std["o"]) / np.asarray(oc.std_white["o"])
    assert np.allclose(ratio, np.sqrt(np.maximum(F, 1.0)), rtol=1e-9)
