"""Samples that never arrived (imugraph.factors.gaps): the variance of a held sample over a gap, the keyframe
layout that puts every gap between keyframes, the per-sample blend that keeps a gap's closing error out of the
samples before it, and the batch and stream paths on a recording with drops."""

import dataclasses

import numpy as np
import pytest

from imugraph.calibration.ml import Options, calibrate
from imugraph.evaluate import orientation_error
from imugraph.factors.gaps import GAP_RATE_WALK, gap_variance
from imugraph.factors.gyro import keyframe_layout, preintegrate
from imugraph.graphs.orientation_init import sample_orientations
from imugraph.sim.scenario import distorted_session


def test_gap_variance_known_answer():
    """q² τ³ / 3 on the long steps only (τ = Δt − T), 0 on steps up to 1.5 T."""
    T = 0.01
    dt = np.array([T, 1.4 * T, 0.5, T, 1.6 * T])
    v = gap_variance(dt, T, 3.0)
    assert v[0] == 0.0 and v[1] == 0.0 and v[3] == 0.0
    assert v[2] == pytest.approx(9.0 * 0.49**3 / 3.0, rel=1e-12)
    assert v[4] == pytest.approx(9.0 * (0.6 * T) ** 3 / 3.0, rel=1e-12)


def test_gap_variance_is_the_integral_of_a_random_walk():
    """Monte Carlo of eq. (G1): a rate doing a random walk of density q over τ, held at its start value; the
    integrated error's variance is q² τ³ / 3 (5 % with 20 000 paths)."""
    rng = np.random.default_rng(0)
    q, tau, m = 3.0, 0.5, 200
    h = tau / m
    w = np.cumsum(rng.normal(0.0, q * np.sqrt(h), (20000, m)), axis=1)     # rate change since the gap start
    err = w.sum(axis=1) * h                                                 # ∫ (ω(t) − ω_held) dt
    assert np.var(err) == pytest.approx(gap_variance(np.array([tau + 0.01]), 0.01, q)[0], rel=0.05)


def test_keyframe_layout_puts_gaps_between_keyframes():
    n, stride = 100, 10
    dt = np.full(n, 0.01)
    dt[[24, 61]] = 0.3                                   # samples 25 and 62 come after a gap
    kf, skf = keyframe_layout(n, stride, dt)
    assert {25, 62} <= set(kf.tolist()) and kf[-1] == n - 1 and np.all(np.diff(kf) > 0)
    # no interval holds a gap inside: every gap step is an interval's last step
    for a, b in zip(kf[:-1], kf[1:]):
        assert np.all(dt[a:b - 1] < 0.015)
    assert np.array_equal(kf[:3], [0, 10, 20]) and np.array_equal(kf[3:6], [25, 35, 45])     # grid restarts
    assert np.array_equal(skf, np.searchsorted(kf, np.arange(n), side="right") - 1)
    # without gaps (or without dt) the layout is the old one
    assert np.array_equal(keyframe_layout(n, stride, np.full(n, 0.01))[0], keyframe_layout(n, stride)[0])


def test_samples_before_a_gap_keep_the_forward_rotation():
    """The interval ending in the gap: the keyframes disagree with its ΔR by the gap's error; the samples before
    the gap stay R_k ΔR_kj (u = 0); a normal interval still blends."""
    rng = np.random.default_rng(1)
    n = 60
    dt = np.full(n, 0.01)
    dt[29] = 0.5
    w = rng.normal(0.0, 1.0, (n, 3))
    kf, skf = keyframe_layout(n, 15, dt)
    pre = preintegrate(w, dt, kf, skf, np.zeros(3), np.full(3, 0.01))
    assert pre.gap_end is not None and pre.gap_end.tolist() == [False, True, False, False]
    nRk = np.stack([np.eye(3)] + [np.eye(3)] * (len(kf) - 1))        # keyframes that ignore the gyro entirely
    from imugraph.geometry import quat_to_rotmat
    nRb = quat_to_rotmat(sample_orientations(nRk, pre))
    assert np.allclose(nRb[15:30], pre.kRb[15:30], atol=1e-12)         # forward only in the gap interval
    assert not np.allclose(nRb[1:15], pre.kRb[1:15], atol=1e-6)        # blended in a normal one


def _drop(session, starts_s, length_s):
    keep = np.ones(session.n, bool)
    for s0 in starts_s:
        keep[(session.t >= session.t[0] + s0) & (session.t < session.t[0] + s0 + length_s)] = False
    return dataclasses.replace(session, t=session.t[keep], gyr=session.gyr[keep], acc=session.acc[keep],
                               mag=session.mag[keep], quat=session.quat[keep], movement=None), keep


def _rms(est, session):
    return orientation_error(est.quat, session.quat, None, session.rate).rms_deg


def test_batch_with_drops_stays_close_to_the_clean_run():
    """Three 0.5 s drops during motion (simulation, 100 Hz): calibrate + smooth within 0.3° of the clean run;
    with the missing time trusted like measured time (q = 0) it is off by degrees."""
    session, _ = distorted_session(3, duration_s=60.0)
    clean = _rms(calibrate(session, Options()), session)
    gapped, _ = _drop(session, (15.0, 30.0, 45.0), 0.5)
    with_model = _rms(calibrate(gapped, Options()), gapped)
    assert with_model < clean + 0.3, (clean, with_model)


def test_without_the_gap_model_drops_cost_degrees():
    """The same recording with Options(gap_model=False) (missing time trusted like measured time, the old layout):
    the check above can fail (5.8° measured against 0.25° clean)."""
    session, _ = distorted_session(3, duration_s=60.0)
    gapped, _ = _drop(session, (15.0, 30.0, 45.0), 0.5)
    clean = _rms(calibrate(session, Options()), session)
    assert _rms(calibrate(gapped, Options(gap_model=False)), gapped) > clean + 0.3


def test_one_long_drop_restarts_the_start_values():
    """A single 5 s drop (simulation): the start values restart from the measured TRIAD after the gap
    (complementary_keyframes); carrying the held rate's ΔR across it left the solver 13° RMS off (review R1)."""
    session, _ = distorted_session(3, duration_s=60.0)
    gapped, _ = _drop(session, (30.0,), 5.0)
    assert _rms(calibrate(gapped, Options()), gapped) < 3.0


def test_a_keyframe_without_up_borrows_its_neighbours():
    """keyframe_directions: a keyframe whose rows sum to a zero specific force (a placeholder row alone in its
    interval, as Rasteiro's first row) takes the nearest keyframe's up instead of a NaN TRIAD."""
    from imugraph.graphs.orientation_init import complementary_keyframes, keyframe_directions

    n = 40
    dt = np.full(n, 0.01)
    dt[0] = 0.3                                            # row 0 alone before a gap: a keyframe of its own
    kf, skf = keyframe_layout(n, 10, dt)
    pre = preintegrate(np.zeros((n, 3)), dt, kf, skf, np.zeros(3), np.full(3, 0.01))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    acc[0] = 0.0
    mag = np.tile([0.3, 0.0, -0.9], (n, 1))
    up, _ = keyframe_directions(pre, acc, mag)
    assert kf[1] == 1 and np.allclose(up[0] / np.linalg.norm(up[0]), [0.0, 0.0, 1.0])
    assert np.all(np.isfinite(complementary_keyframes(pre, acc, mag)))
