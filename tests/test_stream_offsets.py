"""Windowed hard-iron offsets in the stream and the majority's hard iron (imugraph.graphs.stream_offsets)."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from imugraph.factors.magnetometer import magnetometer_rows
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_calstate import CAL_KEY, cal_mag_factor, cal_mag_jacobians, theta_of
from imugraph.graphs.stream_offsets import WindowOffsets, joint_estimate, offset_key, swap_hard_iron
from imugraph.sim.scenario import distorted_session


def test_joint_estimate_is_least_squares_without_the_pin():
    """Known answer: on a linear Gaussian problem in Ψ = (θ (13), Δo (3)), the pinned solution and its joint
    information turned into eq. (2) equal numpy's least squares with the weak prior on θ instead of the pin."""
    rng = np.random.default_rng(3)
    n = 16
    A = rng.normal(size=(60, n))
    b = rng.normal(size=60)
    theta0 = rng.normal(size=13)
    pin_sig, weak_sig = np.full(13, 1e-4), rng.uniform(0.5, 2.0, 13)
    # pinned: min |A Ψ − b|² + |(θ − θ₀)/σ_p|²
    P = np.vstack([A, np.hstack([np.diag(1 / pin_sig), np.zeros((13, 3))])])
    psi_hat = np.linalg.lstsq(P, np.r_[b, theta0 / pin_sig], rcond=None)[0]
    J = P.T @ P
    psi, cov = joint_estimate(psi_hat, J, theta0, pin_sig, weak_sig)
    W = np.vstack([A, np.hstack([np.diag(1 / weak_sig), np.zeros((13, 3))])])
    ref = np.linalg.lstsq(W, np.r_[b, theta0 / weak_sig], rcond=None)[0]
    assert np.allclose(psi, ref, atol=1e-6)
    assert np.allclose(cov, np.linalg.inv(W.T @ W), rtol=1e-6, atol=1e-9)


def test_swap_hard_iron_adds_the_offset_and_its_covariance():
    """o + Δo and Var(o + Δo) = Var o + Var Δo + Cov(o, Δo) + Cov(Δo, o), written out by hand."""
    rng = np.random.default_rng(4)
    psi = rng.normal(size=16)
    L = rng.normal(size=(16, 16))
    cov = L @ L.T
    th, c = swap_hard_iron(psi, cov)
    assert np.allclose(th[:9], psi[:9]) and np.allclose(th[12], psi[12])
    assert np.allclose(th[9:12], psi[9:12] + psi[13:16])
    var_o = cov[9:12, 9:12] + cov[13:, 13:] + cov[9:12, 13:] + cov[13:, 9:12]
    assert np.allclose(c[9:12, 9:12], var_o)
    assert np.allclose(c[:9, 9:12], cov[:9, 9:12] + cov[:9, 13:])
    assert np.allclose(c[:9, :9], cov[:9, :9])


def test_fast_jacobians_equal_the_batch_rows():
    """cal_mag_jacobians (written out) = factors.magnetometer.magnetometer_rows of one mean 'sample' (1e-12)."""
    rng = np.random.default_rng(5)
    for _ in range(5):
        R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
        M = gtsam.Rot3.Expmap(0.1 * rng.normal(size=3)).matrix()
        d = 0.01 * rng.normal(size=3)
        th = np.r_[(45 * np.eye(3) + rng.normal(size=(3, 3))).ravel(), rng.normal(size=3), 1.2]
        y = 40 * rng.normal(size=3)
        X, V = magnetometer_rows(M.T[None], np.zeros(1, int), R[None], th, y[None], d[None])
        e, J_pose, J_d, J_th = cal_mag_jacobians(R, d, th, M, y)
        assert np.allclose(e, X[0, :, -1], atol=1e-12, rtol=0)
        assert np.allclose(J_pose[:, :3], X[0, :, :3] @ V[0], atol=1e-12, rtol=0) and not J_pose[:, 3:].any()
        assert np.allclose(J_d, X[0, :, :3] @ R.T, atol=1e-12, rtol=0)
        assert np.allclose(J_th, X[0, :, 3:16], atol=1e-12, rtol=0)


def _factor_error(f, values) -> float:
    return float(f.error(values))


def test_offset_factor_residual_and_jacobian():
    """With Δo_w: a new window's factor has zero residual at the pin (Δo_w starts at minus the residual); the
    linearised error at a moved Δo_w equals ½|W (e + δ)|² of the model written out (no Huber: small residual)."""
    cal = distorted_session(3, 12.0, 50.0)[1].to_calibration()
    th = theta_of(cal)
    kRb = np.tile(np.eye(3), (5, 1, 1))
    off = np.array([3.0, -2.0, 1.0])
    y = np.tile(cal.D @ cal.n_mag + cal.o + off, (5, 1))
    sig = np.full(3, 0.5)
    pose = gtsam.Pose3()
    info = {}
    f, rows = cal_mag_factor(1, pose, 2, np.zeros(3), th, kRb, y, sig, 2.0, th, -1.0, offset_key(0), None, info)
    assert rows is None and CAL_KEY not in list(f.keys()) and offset_key(0) in list(f.keys())
    assert np.allclose(info["offset"], off, atol=1e-9) and info["r2"] < 1e-18 and info["n"] == 5
    v = gtsam.Values()
    v.insert(1, pose)
    v.insert(2, np.zeros(3))
    v.insert(offset_key(0), off)
    assert _factor_error(f, v) < 1e-18
    delta = np.array([0.01, 0.02, -0.01])
    v.update(offset_key(0), off + delta)
    w = np.sqrt(5) / sig                                           # whitening by σ_y / √n
    assert np.isclose(_factor_error(f, v), 0.5 * np.sum((w * delta) ** 2), rtol=1e-9)
    # with θ too (a window that informs θ): pose, θ, Δo_w (d_k held)
    f2, rows2 = cal_mag_factor(1, pose, 2, np.zeros(3), th, kRb, y, sig, 2.0, th, None, offset_key(0), off, {})
    assert set(f2.keys()) == {1, CAL_KEY, offset_key(0)} and rows2 is not None


def test_window_offsets_majority_rule():
    """The largest window is the normal state when its samples outnumber the normal keyframes' and its residual RMS
    is within EXPLAINED (3) × theirs; its key must still be in the solver."""
    wo = WindowOffsets(40.0)
    g, v, st = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    for _ in range(10):
        wo.normal(30, 2.0)
    wo.added("a", np.zeros(3), 30, 4.0, g, v, st, 1.0)
    for _ in range(10):
        wo.added("a", np.zeros(3), 30, 4.0, g, v, st, 2.0)       # 330 > 300 samples, RMS 2 ≤ 3 × √2
    assert wo.majority(lambda k: True) == 0 and wo.majority(lambda k: False) is None
    assert st[offset_key(0)] == 2.0 and v.exists(offset_key(0)) and g.size() == 1     # key, prior once
    wo.added("b", np.zeros(3), 600, 400.0, g, v, st, 3.0)        # larger, but not explained (RMS 20 > 3 √2)
    assert wo.largest == 1 and wo.majority(lambda k: True) is None
    assert wo.keep(lambda k: True) == (offset_key(1),)


def test_stream_reports_the_majority_hard_iron():
    """Simulation (2 s chain lag, θ a graph state): the start calibration describes an attached magnet (o₀ = o + Δ,
    as BROAD 32's bootstrap), the magnet comes off at 14 s. With disturb_offsets the detector's window gets its own
    offset, becomes the majority after ≈ 28 s, and the reported o at the end is the true one within 3 std (and far
    nearer than the start); without, the reported o stays the magnet's."""
    session, truth = distorted_session(3, 42.0, 50.0)
    cal_true = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal_true.D))))
    delta = scale * np.array([0.3, -0.25, 0.35])
    mag = session.mag.copy()
    on = session.t < session.t[0] + 14.0
    mag[on] += delta
    start = replace(cal_true, o=cal_true.o + delta)

    def run(offsets: bool):
        opt = StreamOptions(lag_s=2.0, calib_states=True, disturb_detect=True, disturb_offsets=offsets)
        sm = StreamSmoother(start, session.rate, opt, start_window_s=10.0)
        for row in zip(session.t, session.gyr, session.acc, mag):
            sm.push(*row)
        sm.finish()
        return sm

    sm = run(True)
    hist = sm.calibration_history
    assert sm.stats.disturbances >= 1 and sm.stats.failed_updates == 0
    assert hist[-1]["normal_window"] == 0 and hist[2]["normal_window"] is None
    o, std = sm.cal.o, sm.cal.std["o"]
    assert np.all(np.abs(o - cal_true.o) < 3 * std + 1e-9)
    assert np.max(np.abs(o - cal_true.o)) < 0.1 * np.max(np.abs(delta))
    off = run(False)
    assert np.max(np.abs(off.cal.o - cal_true.o)) > 0.8 * np.max(np.abs(delta))


def test_final_graph_holds_each_window_keyframe_once():
    """Full iSAM2 with disturb_offsets: a new window's Δo_w prior enters the update's graph before the keyframe's
    magnetometer factor. The end-of-stream graph (`_final_graph`: the magnetometer factors re-issued exact) must then
    replace the keyframe's once-linearised factor, not the prior: every window keyframe on its offset key once, and
    the offset's prior kept (before the fix: the first keyframe of each window twice and the prior gone; BROAD 30's
    smoothed output 0.132° from the same-model smooth_fixed)."""
    session, truth = distorted_session(3, 30.0, 50.0)
    cal = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    mag = session.mag.copy()
    on = (session.t > session.t[0] + 14.0) & (session.t < session.t[0] + 20.0)
    mag[on] += scale * np.array([0.3, -0.25, 0.35])
    opt = StreamOptions(lag_s=None, calib_states=True, disturb_detect=True, disturb_offsets=True)
    sm = StreamSmoother(cal, session.rate, opt, start_window_s=8.0)
    for row in zip(session.t, session.gyr, session.acc, mag):
        sm.push(*row)
    sm.finish()
    assert sm.stats.disturbances >= 1 and sm.stats.failed_updates == 0
    okeys = {okey for okey in sm._mag_okey.values()}
    assert okeys
    graph = sm._final_graph()
    on_key = {okey: [] for okey in okeys}
    for i in range(graph.size()):
        ks = list(graph.at(i).keys())
        for okey in okeys & set(ks):
            on_key[okey].append(ks)
    for okey in okeys:
        n_kf = sum(1 for k, o in sm._mag_okey.items() if o == okey)
        with_pose = [ks for ks in on_key[okey] if len(ks) > 1]
        priors = [ks for ks in on_key[okey] if ks == [okey]]
        assert len(with_pose) == n_kf            # each window keyframe's magnetometer factor once
        assert len(priors) == 1                  # the offset's prior N(0, (2 × scale)²) kept
