"""The fast per-sample / per-interval arithmetic of a stream (imugraph.graphs.stream_interval) against the batch
path's functions and gtsam, and the constant-memory state of a fixed-lag stream without history."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.errors import SessionError
from imugraph.factors.gaps import GAP_ACC_WALK, GAP_RATE_WALK
from imugraph.factors.gyro import preintegrate
from imugraph.factors.velocity import velocity_increments
from imugraph.graphs.cpp_velocity import gauss_markov_factors
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_interval import (gauss_markov_factor, interval_preintegration, q2R, qmul, qstep,
                                             row3)
from imugraph.sim.scenario import distorted_session


def _interval(rng, n=29, gap=True):
    t = np.cumsum(rng.uniform(0.0033, 0.0037, n + 1))
    if gap:
        t[n // 2:] += 0.01                                    # a gap of ≈ 3 samples inside the interval
    w = rng.normal(0.0, 2.0, (n + 1, 3))
    a = rng.normal(0.0, 4.0, (n + 1, 3)) + [0.0, 0.0, 9.81]
    return t, w, a


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_interval_preintegration_is_the_batch_one(seed):
    """Equal (1e-12) to factors.gyro.preintegrate and factors.velocity.velocity_increments on the same
    interval laid out as the stream does (keyframes at samples 0 and n)."""
    rng = np.random.default_rng(seed)
    t, w, a = _interval(rng, gap=seed == 1)
    n = len(t) - 1
    b = rng.normal(0.0, 0.02, 3)
    sg, sa, kappa, kappa_a = np.array([0.004, 0.005, 0.006]), np.array([0.05, 0.06, 0.07]), 0.01, 0.02
    steps = np.diff(t)
    dt = np.append(steps, np.median(steps))
    kf, skf = np.array([0, n]), np.r_[np.zeros(n, int), 1]
    pre = preintegrate(w, dt, kf, skf, b, sg, kappa)
    dv, sig_dv = velocity_increments(pre.kRb, skf, a, dt, 2, sa, kappa_a)
    # the stream is told the nominal rate; the batch takes it as the median step (gaps eq. G1 on seed 1's gap)
    gap = (1.0 / np.median(dt), GAP_RATE_WALK, GAP_ACC_WALK)
    kRb, dR, cov, dt_k, dv2, sig2, q = interval_preintegration(t, w[:n], a[:n], b, sg, kappa, sa, kappa_a, gap)
    assert np.allclose(kRb, pre.kRb[:n], atol=1e-12) and np.allclose(dR, pre.delta_R[0], atol=1e-12)
    assert np.allclose(cov, pre.cov[0], rtol=1e-10, atol=1e-18)
    assert dt_k == pytest.approx(pre.dt[0], abs=1e-15)
    assert np.allclose(dv2, dv[0], atol=1e-12) and sig2 == pytest.approx(sig_dv[0], rel=1e-12)
    assert np.allclose(q2R(q), kRb, atol=1e-12) and np.all(q[:, 0] >= 0)


def test_qstep_is_gtsam_expmap():
    """q ⊗ Exp(ω dt) against gtsam's Rot3.Expmap and compose, for ordinary and tiny (series) rotations."""
    rng = np.random.default_rng(5)
    q = (1.0, 0.0, 0.0, 0.0)
    R = gtsam.Rot3()
    for scale in (3.0, 1e-9, 0.5, 1e-12, 2.0):
        w, dt = rng.normal(0.0, scale, 3), 0.0035
        q = qstep(q, *w, dt)
        R = R.compose(gtsam.Rot3.Expmap(w * dt))
        assert np.allclose(q2R(np.array([q]))[0], R.matrix(), atol=1e-13)
    assert np.allclose(qmul(q, (q[0], -q[1], -q[2], -q[3])), (1.0, 0.0, 0.0, 0.0), atol=1e-14)


def test_row3_accepts_vectors():
    assert row3([1, 2, 3]) == (1.0, 2.0, 3.0)
    assert row3(np.array([[1.0, 2.0, 3.0]])) == (1.0, 2.0, 3.0)
    with pytest.raises(ValueError):
        row3([1.0, 2.0])


def test_gauss_markov_factor_is_the_batch_one():
    """The interval factor equals cpp_velocity.gauss_markov_factors' (error at random velocities)."""
    rng = np.random.default_rng(7)
    ref = gauss_markov_factors(np.array([0.1]), 0.5, 2.0)[1]
    mine = gauss_markov_factor(keys.vel(0), keys.vel(1), 0.1, 0.5, 2.0)
    for _ in range(3):
        v = gtsam.Values()
        v.insert(keys.vel(0), rng.normal(0.0, 1.0, 3))
        v.insert(keys.vel(1), rng.normal(0.0, 1.0, 3))
        assert mine.error(v) == pytest.approx(ref.error(v), rel=1e-12) and mine.error(v) > 0


@pytest.fixture(scope="module")
def sim():
    session, truth = distorted_session(4, 40.0, 100.0)
    return session, truth.to_calibration()


def test_filtered_is_newest_keyframe_times_gyro(sim):
    """push returns nRk (the solver's newest keyframe) composed with the gyro integrated since, at the current
    bias estimate — recomputed here with gtsam's Rot3 (independent of the float quaternions)."""
    session, cal = sim
    sm = StreamSmoother(cal, session.rate, StreamOptions(lag_s=2.0, fixed_lag_solver="incremental"))
    stop = 1000 + sm.stride // 2
    for i in range(stop):
        q = sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    first = stop - len(sm._buf)                         # the newest keyframe's sample
    R = sm._nRk
    b = np.asarray(sm._b_gyr_est)
    for j in range(first, stop - 1):
        R = R.compose(gtsam.Rot3.Expmap((session.gyr[j] - b) * (session.t[j + 1] - session.t[j])))
    qr = R.toQuaternion()
    expect = np.array([qr.w(), qr.x(), qr.y(), qr.z()])
    assert np.allclose(q, expect * np.sign(expect[0]), atol=1e-12)


def test_lag_without_history_holds_constant_state(sim, feed_stream):
    """Fixed lag, keep_history=False: the per-keyframe state kept is bounded by the window (plus the
    keyframes the online calibration still awaits), no magnetometer-factor index is kept, and asking for
    the whole smoothed trajectory is a SessionError."""
    session, cal = sim
    opt = StreamOptions(lag_s=2.0, fixed_lag_solver="incremental", keep_history=False)
    sm = StreamSmoother(cal, session.rate, opt)
    sizes = feed_stream(sm, session, 500, lambda sm: len(sm._smoothed_kf))
    window = int(round(max(opt.lag_s, opt.calib_delay_s) * opt.keyframe_hz)) + 3
    assert sm._k > 10 * window and max(sizes) <= window + 2
    assert not sm._mag_index and not sm._hist_kRb and sm.stats.failed_updates == 0
    with pytest.raises(SessionError):
        sm.smoothed()
