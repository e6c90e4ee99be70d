"""Incremental runs (imugraph.graphs.stream, stream_run, `imugraph stream`): the same model as the batch
smoother solved by iSAM2 / a fixed-lag smoother, arrival problems counted, the CLI's four files."""

import json

import numpy as np
import pytest

from imugraph.cli import main
from imugraph.errors import SessionError
from imugraph.evaluate import orientation_error
from imugraph.graphs.cpp_smoother import smooth_fixed
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_run import stream_session
from imugraph.sim.scenario import distorted_session

RATE = 100.0
FIXED = StreamOptions(online_calibration=False, field_sigma=None)   # the batch comparisons: the same (true)
# calibration, and no field perturbation (smooth_fixed has none; stream_field is tested in test_stream_field.py)


@pytest.fixture(scope="module")
def case():
    session, truth = distorted_session(3, 30.0, RATE)
    cal = truth.to_calibration()
    batch = smooth_fixed(session, cal, rotation_tol_deg=0.001)     # converged well below the tolerances
    return session, cal, batch, _err(batch, session.quat)


def _err(q, ref, align=True):
    if align:
        return orientation_error(q, ref, None, RATE).rms_deg
    return orientation_error(q, ref, None, RATE, heading=False, max_shift=0.0).rms_deg


def test_isam2_smoothed_is_the_batch_solution(case):
    """One model, two solvers: iSAM2 reaches the batch optimum up to its relinearisation threshold (0.01 rad:
    linearisation points may stay that far off). The issue's target is 0.1° RMS; and the solver difference
    must stay well below the estimation error itself (both against the truth)."""
    session, cal, batch, batch_err = case
    r = stream_session(session, cal, FIXED)
    gap = _err(r.smoothed, batch, align=False)
    assert gap < 0.1 and gap < 0.25 * batch_err
    assert r.smoothed.shape == (session.n, 4) and r.filtered.shape == (session.n, 4)
    assert r.timing["updates"] == int(np.ceil((session.n - 1) / 10))      # one update per keyframe interval
    assert r.counts["failed_updates"] == 0          # every iSAM2 update solved (none fell back to prediction)
    # filtered: causal, so worse than smoothed, but bounded (the magnetometer holds heading, gravity tilt)
    f_err = _err(r.filtered, session.quat)
    assert batch_err <= f_err < max(3.0 * batch_err, 0.5)


def test_isam2_newest_keyframe_is_the_filtering_optimum(case):
    """The filtered output rests on iSAM2's estimate of the newest keyframe: mid-stream it must equal the
    optimum of all factors received so far (Levenberg–Marquardt to convergence on iSAM2's own factors),
    not a stale or failed update. (Before the weak pose prior every update threw IndeterminantLinearSystem
    and the filtered output was gyro dead reckoning.)"""
    import gtsam

    from imugraph.graphs.cpp_velocity import pose_key

    session, cal, _, _ = case
    sm = StreamSmoother(cal, RATE, FIXED, g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
    for i in range(session.n // 2):
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    assert sm.stats.failed_updates == 0
    est = sm._solver.calculateEstimate()
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    opt = gtsam.LevenbergMarquardtOptimizer(sm._solver.getFactorsUnsafe(), est, params).optimize()
    k = sm._k
    gap = np.rad2deg(np.linalg.norm(gtsam.Rot3.Logmap(est.atPose3(pose_key(k)).rotation()
                                                      .between(opt.atPose3(pose_key(k)).rotation()))))
    assert gap < 0.1


def test_fixed_lag_close_to_batch(case):
    """A 2 s window sees the next 2 s of data for every keyframe (> the 2 s velocity correlation time):
    its smoothed output is within a fraction of a degree of the full batch solution."""
    session, cal, batch, batch_err = case
    opt = StreamOptions(lag_s=2.0, online_calibration=False, fixed_lag_solver="batch", field_sigma=None)
    r = stream_session(session, cal, opt)
    assert _err(r.smoothed, batch, align=False) < 0.5
    assert _err(r.smoothed, session.quat) < batch_err + 0.2
    assert r.counts["failed_updates"] == 0


@pytest.mark.parametrize("solver", ["incremental", "chain"])
def test_incremental_fixed_lag_close_to_batch(case, solver):
    """gtsam's IncrementalFixedLagSmoother (iSAM2 inside, weak pose prior), or the chain-ordered lag of
    stream_lag, as the --lag solver: no failed update on this session, and the same accuracy bounds as the
    batch fixed-lag smoother."""
    session, cal, batch, batch_err = case
    opt = StreamOptions(lag_s=2.0, online_calibration=False, fixed_lag_solver=solver, field_sigma=None)
    r = stream_session(session, cal, opt)
    assert r.counts["failed_updates"] == 0
    assert _err(r.smoothed, batch, align=False) < 0.5
    assert _err(r.smoothed, session.quat) < batch_err + 0.2
    with pytest.raises(SessionError):
        StreamSmoother(cal, RATE, StreamOptions(lag_s=2.0, fixed_lag_solver="fast"))


def test_arrival_problems_are_counted_and_harmless(case):
    """Duplicates, swapped neighbours, a gap, invalid rows and a 4× slower magnetometer: every one is
    counted as injected, nothing raises, and the orientation stays close to the clean run's accuracy."""
    session, cal, _, batch_err = case
    n = session.n
    mag = session.mag.copy()
    mag[np.arange(n) % 4 != 0] = np.nan                       # magnetometer at a quarter of the gyro rate
    gap = np.arange(1500, 1520)                                # 20 samples never arrive
    order = [i for i in range(n) if i not in set(gap)]
    swapped = range(100, len(order) - 1, 97)                   # a sample overtaken by its successor
    for pos in swapped:
        order[pos], order[pos + 1] = order[pos + 1], order[pos]
    swaps = len(swapped)
    near = {p + d for p in swapped for d in (-1, 0, 1, 2)}
    dup_rows = [order[p] for p in range(50, len(order), 211) if p not in near]   # delivered twice
    arrivals = []
    for i in order:
        arrivals.append(i)
        if i in dup_rows:
            arrivals.append(i)
    sm = StreamSmoother(cal, RATE, StreamOptions(), g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
    bad_gyr = np.array([np.nan, 0.0, 0.0])
    for j, i in enumerate(arrivals):
        q = sm.push(session.t[i], session.gyr[i], session.acc[i], mag[i])
        assert q.shape == (4,) and np.all(np.isfinite(q))
        if j in (10, 2000):
            sm.push(session.t[i] + 0.001, bad_gyr, session.acc[i], None)
    sm.finish()
    c = sm.stats
    assert c.duplicates == len(dup_rows)
    assert c.invalid == 2
    assert c.late_inserted + c.late_dropped == swaps and c.late_inserted > 0
    # a late sample whose interval had closed is dropped: it leaves a hole like the gap's
    assert c.missing == len(gap) + c.late_dropped and 1 <= c.gaps <= 1 + c.late_dropped
    assert c.accepted == n - len(gap) - c.late_dropped
    n_mag = int(np.sum(np.isfinite(mag[order, 0])))
    assert n_mag - c.late_dropped <= c.mag_samples <= n_mag
    smoothed, t_kept = sm.smoothed(), sm.sample_times()
    assert smoothed.shape == (c.accepted, 4) and np.all(np.diff(t_kept) > 0)
    kept = np.searchsorted(session.t, t_kept)
    assert np.allclose(session.t[kept], t_kept)
    assert _err(smoothed, session.quat[kept]) < batch_err + 0.3


def test_push_before_and_after(case):
    session, cal, _, _ = case
    sm = StreamSmoother(cal, RATE)
    assert np.all(np.isnan(sm.push(np.nan, np.zeros(3), np.zeros(3))))   # nothing yet: NaN, not an error
    q = sm.push(0.0, session.gyr[0], session.acc[0], session.mag[0])
    assert np.isclose(np.linalg.norm(q), 1.0)
    sm.finish()
    assert sm.smoothed().shape == (1, 4)
    assert sm.stats.invalid == 1


def test_cli_writes_the_four_files(tmp_path, capsys):
    session, _ = distorted_session(4, 30.0, 50.0)
    path = tmp_path / "s.npz"
    np.savez(path, t=session.t, gyr=session.gyr, acc=session.acc, mag=session.mag, quat=session.quat)
    out = tmp_path / "out"
    assert main(["stream", str(path), "--out", str(out), "--bootstrap-s", "20", "--lag", "2", "--quiet"]) == 0
    assert "real time" in capsys.readouterr().out
    for name in ("orientation.npz", "orientation_filtered.npz"):
        with np.load(out / name) as z:
            assert z["quat"].shape == (session.n, 4) and np.allclose(z["t"], session.t)
            assert _err_rate(z["quat"], session.quat, 50.0) < 3.0
    hist = json.loads((out / "calibration_history.json").read_text())
    assert len(hist["calibration_history"]) >= 2 and np.asarray(hist["start"]["D"]).shape == (3, 3)
    if StreamOptions().calib_states:     # θ a graph state (default): calibration.json is the last streamed estimate
        written = hist["calibration_history"][-1]
    else:                                # the refit: the last refit swapped into the factors
        written = ([r for r in hist["calibration_history"] if r["applied"]] or [hist["start"]])[-1]
    assert np.allclose(written["D"], json.loads((out / "calibration.json").read_text())["D"])
    row = hist["calibration_history"][-1]
    assert np.asarray(row["std"]["D"]).shape == (3, 3) and row["t"] > 20.0
    timing = json.loads((out / "timing.json").read_text())
    assert {"updates", "seconds", "p50_ms", "p99_ms"} <= set(timing) and timing["updates"] > 0
    assert timing["bootstrap_samples"] == int(np.sum(session.t <= session.t[0] + 20.0))
    cal = json.loads((out / "calibration.json").read_text())
    assert np.asarray(cal["D"]).shape == (3, 3)
    for name in ("stream_calibration.png", "stream_orientation.png", "stream_timing.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name


def _err_rate(q, ref, rate):
    return orientation_error(q, ref, None, rate).rms_deg


@pytest.mark.parametrize("args", [["--lag", "-1"], ["--bootstrap-s", "x"]])
def test_cli_bad_options_exit_2(tmp_path, args, capsys):
    assert main(["stream", str(tmp_path / "missing.npz"), *args]) == 2


def test_real_broad_updates_all_solve():
    """BROAD 01, first 10 s at 286 Hz with a sphere calibration (the trial is close to calibrated, |m| ≈ 44 µT,
    dip ≈ 69°): no iSAM2 update may fail (on this trial every update once threw IndeterminantLinearSystem,
    and the filtered output silently became gyro dead reckoning). Skips without the shared data."""
    from benchmarks.common import broad_trials, load_broad_trial, trial_number
    from imugraph.calibration.result import Calibration

    paths = [p for p in broad_trials() if trial_number(p) == 1]
    if not paths:
        pytest.skip("BROAD data not present")
    s = load_broad_trial(paths[0]).slice(0, 2860)
    cal = Calibration(D=44.0 * np.eye(3), o=np.zeros(3), dip_deg=69.0,
                      noise={"gyr": np.full(3, 0.0018), "acc": np.full(3, 0.05), "mag": np.full(3, 0.9)})
    r = stream_session(s, cal, StreamOptions())
    assert r.counts["failed_updates"] == 0
    assert np.all(np.isfinite(r.filtered)) and np.all(np.isfinite(r.smoothed))
