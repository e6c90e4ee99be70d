"""Causal disturbance windows (imugraph.graphs.stream_disturb, StreamOptions.disturb_detect) and the batch's weak
prior online (StreamOptions.calib_weak_prior; stream_calstate.data_estimate with a prior centre)."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_calib import OnlineMagCalibration
from imugraph.graphs.stream_calstate import data_estimate
from imugraph.graphs.stream_disturb import DisturbanceDetector, field_norm_sigma
from imugraph.graphs.stream_online import weak_prior
from imugraph.sim.scenario import distorted_session

KAPPA = 6.634897    # χ²₁ 0.99 quantile (tables)
H = 15.136705       # χ²₁ 0.9999 quantile (tables)


def _rows(dev: float, n: int = 10) -> np.ndarray:
    """n field rows of norm 1 + dev (D₀ = I, o₀ = 0), in varying directions."""
    u = np.random.default_rng(0).standard_normal((n, 3))
    return (1.0 + dev) * u / np.linalg.norm(u, axis=1, keepdims=True)


def test_cusum_known_answer():
    """(2) by hand: σ_f 0.01, no sample noise, a 3σ step (z² = 9) from interval 3 on: g grows by 9 − κ per interval,
    the alarm rises at the 7th hot interval (g = 7 × 2.365 = 16.56 > h) with the onset at the step's first interval
    minus the pad; after the step g falls by κ per quiet interval (16.56 → 9.93 → 3.29 → 0: the alarm ends at the 3rd),
    and intervals are flagged to the last hot one's end + pad."""
    det = DisturbanceDetector(np.eye(3), np.zeros(3), 0.01, 0.0, pad_s=0.25, max_lag_s=5.0, min_deviation=0.0)
    assert det.kappa == pytest.approx(KAPPA, abs=1e-5) and det.h == pytest.approx(H, abs=1e-5)
    devs = [0.0] * 3 + [0.03] * 8 + [0.0] * 6
    out = [det.step(0.1 * k, 0.1 * (k + 1), _rows(d)) for k, d in enumerate(devs)]
    onsets = [(k, o) for k, (_, o) in enumerate(out) if o is not None]
    assert onsets == [(9, pytest.approx(0.3 - 0.25))]            # the 7th hot interval (3..9), onset 0.3 − pad
    flags = [f for f, _ in out]
    # hot intervals 3..10 end at 1.1 s: flagged while the alarm lasts (to 13) and those starting ≤ 1.1 + 0.25
    assert flags == [False] * 9 + [True] * 5 + [False] * 3
    assert det.windows == 1 and det.spans == [[pytest.approx(0.05), pytest.approx(1.35)]]
    assert not det.alarm


def test_learning_window_sets_sigma_from_the_data():
    """σ_f² = max(model², median ē² / 0.4549) over the learning window (no alarm there): interval means of ±0.04
    give σ_f = 0.04 / √0.4549 = 0.0593; then a 0.04 deviation does not alarm, a 0.3 one at once."""
    det = DisturbanceDetector(np.eye(3), np.zeros(3), 0.015, 0.0, learn_s=2.0, min_deviation=0.0)
    for k in range(20):
        assert det.step(0.1 * k, 0.1 * (k + 1), _rows(0.04 * (-1) ** k)) == (False, None)
    assert det.step(2.0, 2.1, _rows(0.04))[0] is False
    assert det.sigma_f == pytest.approx(0.04 / np.sqrt(0.454936), rel=1e-4)
    assert all(not det.step(0.1 * k, 0.1 * (k + 1), _rows(0.04))[0] for k in range(22, 60))
    flag, onset = det.step(6.0, 6.1, _rows(0.3))
    assert flag and onset is not None


def test_floor_keeps_sustained_small_deviations_quiet():
    """With the batch's 6 % floor (σ_f ≥ 0.06 / √κ = 0.0233): 5.5 % held for 30 s raises no alarm, 8 % held does
    (z² = 11.8 > κ: after ⌈h / (z² − κ)⌉ = 3 intervals)."""
    det = DisturbanceDetector(np.eye(3), np.zeros(3), 0.01, 0.0)
    assert det.sigma_f == pytest.approx(0.06 / np.sqrt(KAPPA), rel=1e-5)
    assert not any(det.step(0.1 * k, 0.1 * (k + 1), _rows(0.055))[0] for k in range(300))
    hits = [det.step(30 + 0.1 * k, 30 + 0.1 * (k + 1), _rows(0.08))[0] for k in range(5)]
    assert hits == [False, False, True, True, True]


def test_without_learning_a_misfit_start_does_not_hide_a_disturbance():
    """learn_sigma=False (StreamOptions.disturb_learn_sigma): a start calibration that misfits its own learning window
    (BROAD 36: ±5.5–8 %; here ē = 0.08 there) no longer sets σ_f — with learning σ_f = 0.08 / √0.4549 = 0.119 and a
    later 7 % deviation never alarms (z² = 0.35); without, σ_f stays at the floor 0.06 / √κ = 0.0233, z² = 9.0 > κ, g
    grows by 2.37 per interval and the alarm rises at the 7th (16.6 > h)."""
    def run(learn: bool):
        det = DisturbanceDetector(np.eye(3), np.zeros(3), 0.01, 0.0, learn_s=2.0, learn_sigma=learn)
        for k in range(20):
            assert det.step(0.1 * k, 0.1 * (k + 1), _rows(0.08)) == (False, None)
        return det, [det.step(2.0 + 0.1 * k, 2.1 + 0.1 * k, _rows(0.07))[0] for k in range(10)]

    det, hits = run(True)
    assert det.sigma_f == pytest.approx(0.08 / np.sqrt(0.454936), rel=1e-4) and not any(hits)
    det, hits = run(False)
    assert det.sigma_f == pytest.approx(0.06 / np.sqrt(KAPPA), rel=1e-5)
    assert hits == [False] * 6 + [True] * 4


def test_field_norm_sigma():
    """σ_d (x along the horizontal field, z up) projected on n̂ = (cos δ, 0, −sin δ)."""
    assert field_norm_sigma((0.015, 0.003, 0.015), 1.2) == pytest.approx(0.015)
    assert field_norm_sigma((0.02, 0.0, 0.01), 0.0) == pytest.approx(0.02)
    assert field_norm_sigma((0.02, 0.0, 0.01), np.pi / 2) == pytest.approx(0.01)


def test_data_estimate_with_a_prior_centre_is_least_squares():
    """Known answer (linear Gaussian): from the pinned solution θ̂, P of (3), eq. (4) with the weak prior about a
    centre c equals numpy's least squares of the data plus that prior."""
    rng = np.random.default_rng(3)
    J, b = rng.standard_normal((40, 13)), rng.standard_normal(40)
    th0, c = rng.standard_normal(13), rng.standard_normal(13)
    pin, weak = np.full(13, 1e-3), rng.uniform(0.5, 2.0, 13)
    A = J.T @ J + np.diag(1 / pin**2)                     # pinned normal matrix
    theta_hat = th0 + np.linalg.solve(A, J.T @ (b - J @ th0))
    theta, cov = data_estimate(theta_hat, np.linalg.inv(A), th0, pin, weak, c)
    ref = np.linalg.lstsq(np.vstack([J, np.diag(1 / weak)]), np.r_[b, c / weak], rcond=None)[0]
    assert np.allclose(theta, ref, atol=1e-6)
    assert np.allclose(cov, np.linalg.inv(J.T @ J + np.diag(1 / weak**2)), atol=1e-8)


def test_weak_prior_is_the_batch_prior():
    """Centre s·I, o = 0, the start's dip; σ D 5 % of s, o 10 %, dip 90° (calibration.ml, weak_theta_fraction 0.05);
    none for an identifiable start. set_prior puts it in the refit's (2) per axis."""
    cal = distorted_session(3, 12.0, 50.0)[1].to_calibration()
    assert weak_prior(cal, 40.0) is None
    weak = replace(cal, coverage={"identifiable": False})
    centre, sig = weak_prior(weak, 40.0)
    assert np.allclose(centre, np.r_[(40.0 * np.eye(3)).ravel(), np.zeros(3), cal.dip_rad])
    assert np.allclose(sig, np.r_[np.full(9, 2.0), np.full(3, 4.0), np.pi / 2])
    oc = OnlineMagCalibration(weak)
    oc.set_prior(centre, sig)
    assert np.allclose(oc.theta0, np.vstack([40.0 * np.eye(3), np.zeros((1, 3))]))
    assert np.allclose(oc.prior_info, np.hstack([np.full((3, 3), 0.25), np.full((3, 1), 1 / 16)]))


def _stream(session, cal, detect: bool):
    sm = StreamSmoother(cal, session.rate, StreamOptions(lag_s=2.0, disturb_detect=detect, calib_memory_s=None,
                                                         calib_prior_from_start=False, calib_states=False,
                                                         disturb_offsets=False),   # the refit's fold-in
                        start_window_s=8.0)
    for row in zip(session.t, session.gyr, session.acc, session.mag):
        sm.push(*row)
    sm.finish()
    h = [r for r in sm.calibration_history if r.get("std")][-1]
    return sm, np.r_[np.ravel(np.asarray(h["D"]) - cal.D), np.asarray(h["o"]) - cal.o]


def test_stream_detects_an_attached_magnet_and_leaves_it_out():
    """Simulation (true start calibration, 2 s lag, refit without forgetting): a body-fixed offset of 15 % of the
    field on every axis during 16–24 s (below the refit's 0.3 × scale sample gate) is found as one window from
    ≈ 16 s (the pad: 0.5 s before) to ≈ 24.5 s, counted, and left out of the refit: its D, o error is then a fraction
    of that with the magnet folded in."""
    session, truth = distorted_session(3, 36.0, 50.0)
    cal = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    mag = session.mag.copy()
    inside = (session.t >= 16.0) & (session.t < 24.0)
    mag[inside] += 0.15 * scale / np.sqrt(3)
    disturbed = session.with_mag(mag)
    sm, err_on = _stream(disturbed, cal, True)
    det = sm._detector
    assert det.windows == 1 and sm.stats.disturbances == 1
    (onset, end), = det.spans
    assert 15.0 <= onset <= 16.2 and 23.9 <= end <= 25.5
    assert 80 <= sm.stats.disturbed_keyframes <= 100 and sm.stats.disturbed_samples > 0.9 * inside.sum()
    _, err_off = _stream(disturbed, cal, False)
    assert np.max(np.abs(err_on)) < 0.5 * np.max(np.abs(err_off))


def test_flagged_keyframe_carries_no_theta():
    """With θ as a graph state, a flagged keyframe's factor (the stream passes gate −1) is on the pose and d_k only,
    with the residual at the pin; unflagged, θ is in it."""
    import gtsam

    from imugraph.graphs.stream_calstate import CAL_KEY, cal_mag_factor, theta_of

    cal = distorted_session(3, 12.0, 50.0)[1].to_calibration()
    th = theta_of(cal)
    kRb = np.tile(np.eye(3), (5, 1, 1))
    y = np.tile(cal.D @ cal.n_mag + cal.o, (5, 1)) + 0.01
    pose = gtsam.Pose3()
    args = (1, pose, 2, np.zeros(3), th, kRb, y, np.full(3, 0.5), 2.0, th)
    flagged, rows_f = cal_mag_factor(*args, -1.0)
    free, rows = cal_mag_factor(*args, None)
    assert CAL_KEY not in list(flagged.keys()) and rows_f is None
    assert CAL_KEY in list(free.keys()) and rows is not None
