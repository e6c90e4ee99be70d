"""StreamOptions.windows_end (session 18, helper W): the end-of-stream graph's disturbance windows re-derived from the
whole stream with the batch's detector and trial verdict (imugraph.graphs.stream_windows_end) instead of the causal
ones; the filtered output untouched. Known answer: a simulated magnet attached to the sensor for a known stretch."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.evaluate import orientation_error
from imugraph.factors.theta import unpack_theta
from imugraph.graphs.cpp_velocity import pose_key
from imugraph.graphs.stream_windows_end import END_KEY0, LEFT_OUT, NORMAL
from imugraph.sim.scenario import distorted_session

import gtsam

ON_S, OFF_S = 20.0, 35.0          # the magnet's stretch (s since the first sample)
from stream_runs import stream_isolated as _stream, truth_rms as _truth_rms


@pytest.fixture(scope="module")
def magnet_window():
    """60 s at 50 Hz; a body-fixed magnet Δ (0.3–0.35 of the field scale per axis, as imugraph.sim.scenario's
    magnet_comes_off_session) on from 20 s to 35 s; the start calibration is the true one (no window in it)."""
    session, truth = distorted_session(5, 60.0, 50.0)
    cal = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    delta = scale * np.array([0.3, -0.25, 0.35])
    rel = session.t - session.t[0]
    on = (rel >= ON_S) & (rel < OFF_S)
    mag = session.mag.copy()
    mag[on] += delta
    s = session.with_mag(mag)
    off, q_off = _stream(s, cal)
    end, q_end = _stream(s, cal, windows_end=True)
    return s, cal, delta, on, (off, q_off), (end, q_end)


def _causal_rows(sm) -> np.ndarray:
    """Samples whose stream factor carried a detector window's Δo_w (every row of such a keyframe interval)."""
    rows = [np.full(len(t), k in sm._mag_okey) for k, t in enumerate(sm._hist_t)]
    return np.concatenate(rows)


def test_filtered_output_unchanged(magnet_window):
    _, _, _, _, (_, q_off), (_, q_end) = magnet_window
    assert np.array_equal(q_off, q_end)


def test_end_window_matches_the_magnet_better_than_the_causal_one(magnet_window):
    """The rows given an offset at the end are the magnet's (±1 sample of padding left), fewer misassigned rows than
    the causal detector's keyframe-granular window; the end offset recovers Δ (the normal state is the true o)."""
    s, cal, delta, on, (off, _), (end, _) = magnet_window
    ext = end._end_extensions[-1]
    n = len(ext.t)
    lab = ext._labels()
    modelled = lab >= 0
    causal = _causal_rows(off)
    assert len(causal) == n
    truth_on = on[:n]
    miss_end = int(np.sum(modelled != truth_on))
    miss_causal = int(np.sum(causal != truth_on))
    w = [x for x in ext.windows if x.explained]
    print(f"misassigned rows: causal {miss_causal}, end {miss_end} of {int(truth_on.sum())} magnet rows; end windows "
          f"{[(round(ext.t[x.start] - s.t[0], 2), round(ext.t[x.stop - 1] - s.t[0], 2)) for x in ext.windows]}")
    assert len(w) == 1
    assert miss_end < miss_causal
    assert miss_end <= 0.02 * truth_on.sum()
    assert np.all(lab[~truth_on] != 0) or np.sum(lab[~truth_on] == 0) <= 2      # padding rows are dropped
    dO = np.asarray(end._final.atVector(gtsam.symbol("w", END_KEY0)), float)
    _, o_n, _ = unpack_theta(ext._theta)
    scale = np.cbrt(abs(np.linalg.det(cal.D)))
    print(f"end Δo_w {dO}, true {delta}; normal o − true o {o_n - cal.o}")
    assert np.abs(dO - delta).max() < 0.02 * scale
    assert np.abs(o_n - cal.o).max() < 0.02 * scale
    assert not np.any(lab == LEFT_OUT) or np.sum(lab == LEFT_OUT) < 0.05 * n


def test_smoothed_error_does_not_grow(magnet_window):
    s, _, _, _, (off, _), (end, _) = magnet_window
    e_off, e_end = _truth_rms(off.smoothed(), s), _truth_rms(end.smoothed(), s)
    print(f"smoothed vs truth: causal windows {e_off:.4f}°, end windows {e_end:.4f}°")
    assert e_end <= e_off * 1.01, (e_end, e_off)


def test_no_disturbance_end_graph_unchanged():
    """Without a disturbance the end detector finds no window and the end graph holds the same factors: the smoothed
    output equals the option's off (within solver round-off)."""
    session, truth = distorted_session(3, 30.0, 50.0)
    cal = truth.to_calibration()
    off, _ = _stream(session, cal)
    end, _ = _stream(session, cal, windows_end=True)
    assert end._end_extensions[-1].windows == []
    d = orientation_error(off.smoothed(), end.smoothed(), None, session.rate, heading=False, max_shift=0.0).rms_deg
    print(f"no window: smoothed on vs off {d:.2e}°")
    assert d < 1e-3
    K = off._k + 1
    R_off = np.stack([off._final.atPose3(pose_key(k)).rotation().matrix() for k in range(K)])
    R_end = np.stack([end._final.atPose3(pose_key(k)).rotation().matrix() for k in range(K)])
    assert np.abs(R_off - R_end).max() < 1e-5


def test_labels_split_rows():
    """A keyframe interval crossing a window edge gets one factor per label; left-out rows none (eq. 1)."""
    from imugraph.calibration.disturbance import Window
    from imugraph.graphs.stream_windows_end import EndWindows

    ext = EndWindows.__new__(EndWindows)
    ext.t = np.arange(20) * 0.1
    ext.windows = [Window(3, 8, offset=np.ones(3), explained=True, drop=np.array([3])),
                   Window(12, 15, offset=None, explained=False)]
    lab = ext._labels()
    assert lab.tolist() == [NORMAL] * 3 + [LEFT_OUT] + [0] * 4 + [NORMAL] * 4 + [LEFT_OUT] * 3 + [NORMAL] * 5
    assert replace(ext.windows[0]).explained


def test_theta_mag_factor_jacobians():
    """windows_end="theta"'s factor: analytic Jacobians (stream_calstate eq. 2, ∂e/∂Δo = I) equal central differences of
    its error on (pose, d_k, θ, Δo_w) (unit whitening: σ_y √n, no Huber)."""
    from imugraph.factors.theta import pack_theta
    from imugraph.graphs.stream_windows_end import theta_mag_factor

    rng = np.random.default_rng(4)
    n = 7
    kRb = np.stack([gtsam.Rot3.Expmap(0.2 * rng.standard_normal(3)).matrix() for _ in range(n)])
    y = 40.0 * rng.standard_normal((n, 3))
    y[2] = np.nan
    keys_ = [pose_key(3), gtsam.symbol("f", 3), gtsam.symbol("c", 0), gtsam.symbol("w", END_KEY0)]
    f = theta_mag_factor(*keys_, kRb, y, np.full(3, np.sqrt(n - 1)), None)
    v = gtsam.Values()
    v.insert(keys_[0], gtsam.Pose3(gtsam.Rot3.Expmap(rng.standard_normal(3)), rng.standard_normal(3)))
    v.insert(keys_[1], 0.02 * rng.standard_normal(3))
    D = 45.0 * (np.eye(3) + 0.05 * rng.standard_normal((3, 3)))
    v.insert(keys_[2], pack_theta(D, 5.0 * rng.standard_normal(3), 1.1))
    v.insert(keys_[3], 3.0 * rng.standard_normal(3))
    A, b = f.linearize(v).jacobian()
    e0 = f.unwhitenedError(v)
    np.testing.assert_allclose(-b, e0, atol=1e-9)
    cols, h = [], 1e-6
    for key, dim in zip(keys_, (6, 3, 13, 3)):
        for j in range(dim):
            dx = np.zeros(dim)
            dx[j] = h
            vp, vm = gtsam.Values(v), gtsam.Values(v)
            if key == keys_[0]:
                vp.update(key, v.atPose3(key).retract(dx))
                vm.update(key, v.atPose3(key).retract(-dx))
            else:
                vp.update(key, v.atVector(key) + dx)
                vm.update(key, v.atVector(key) - dx)
            cols.append((f.unwhitenedError(vp) - f.unwhitenedError(vm)) / (2 * h))
    np.testing.assert_allclose(A, np.stack(cols, axis=1), rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def magnet_window_start_off():
    """The magnet of `magnet_window` (on 20–35 s of 60) and a start calibration 3 % of the field scale off in every
    entry of D and o (as tests/test_stream_l_final_theta.py): windows_end True (θ_n held) and "theta" (θ free)."""
    session, truth = distorted_session(5, 60.0, 50.0)
    cal = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    rel = session.t - session.t[0]
    mag = session.mag.copy()
    mag[(rel >= ON_S) & (rel < OFF_S)] += scale * np.array([0.3, -0.25, 0.35])
    s = session.with_mag(mag)
    rng = np.random.default_rng(0)
    start = replace(cal, D=cal.D + 0.03 * scale * rng.standard_normal((3, 3)),
                    o=cal.o + 0.03 * scale * rng.standard_normal(3))
    held, _ = _stream(s, start, windows_end=True)
    free, _ = _stream(s, start, windows_end="theta")
    return s, cal, scale, held, free


def test_theta_free_end_graph(magnet_window_start_off):
    """With θ free in the end graph (the window's samples inform D and the dip, its o absorbed by Δo_w): the end θ is
    nearer the truth than the normal state's streamed θ_n, and the smoothed output not farther from the truth."""
    from imugraph.graphs.stream_calstate import CAL_KEY

    s, cal, scale, held, free = magnet_window_start_off
    ext = free._end_extensions[-1]
    assert ext._theta_free and len([w for w in ext.windows if w.explained]) == 1
    err = lambda th: np.abs(np.r_[(unpack_theta(th)[0] - cal.D).ravel(), unpack_theta(th)[1] - cal.o]).max() / scale
    e_n, e_free = err(ext._theta), err(np.asarray(free._final.atVector(CAL_KEY)))
    q_held, q_free = _truth_rms(held.smoothed(), s), _truth_rms(free.smoothed(), s)
    print(f"θ max error / scale: streamed θ_n {e_n:.4f}, end graph θ free {e_free:.4f}; smoothed vs truth: θ_n held "
          f"{q_held:.4f}°, θ free {q_free:.4f}°")
    assert e_free < e_n
    assert q_free <= q_held * 1.01


def _smooth_end_calibration(s, sm, cal):
    """smooth_fixed of the stream's end model (benchmarks/stream_vs_batch.py same_model): `cal` with the stream's
    keyframe rate, its d_k process, its raw θ-state factor form, a factor on every closed interval (none on the
    last keyframe), solved to convergence; RMS angle (°) to the stream's smoothed output."""
    from imugraph.graphs.cpp_smoother import smooth_fixed

    o = sm.opt
    K = sm._k + 1
    off = np.full((K, 3), np.nan)
    off[:len(sm._hist_raw)] = 0.0
    q = smooth_fixed(s, cal, keyframe_hz=o.keyframe_hz, field_sigma=o.field_sigma, field_tau=o.field_tau,
                     mag_model="raw", mag_offsets=off, rotation_tol_deg=0.001)
    return orientation_error(sm.smoothed(), q, None, s.rate, heading=False, max_shift=0.0).rms_deg


@pytest.mark.parametrize("mode", [True, "theta"])
def test_end_calibration_reproduces_the_stream(magnet_window_start_off, mode):
    """end_calibration (the end θ — free or θ_n held — and the end windows with their final Δo_w / left-out rows in
    calibration.json's format) given to smooth_fixed reproduces the stream's smoothed output within 0.05° (one
    model, two solvers); the calibration with the start's windows instead (none: the magnet unmodelled) does not."""
    from imugraph.graphs.stream_calstate import CAL_KEY
    from imugraph.graphs.stream_windows_end import end_calibration

    s, cal, scale, held, free = magnet_window_start_off
    sm = held if mode is True else free
    start = sm._cal0
    end = end_calibration(sm, start)
    assert end is not None and [d["source"] for d in end.disturbances] == ["stream_end"]
    assert end.disturbances[0]["modelled"]
    th = np.asarray(sm._final.atVector(CAL_KEY)) if mode == "theta" else sm._end_extensions[-1]._theta
    D, o, dip = unpack_theta(th)
    assert np.allclose(end.D, D) and np.allclose(end.o, o) and np.isclose(end.dip_deg, np.rad2deg(dip))
    if mode == "theta":                       # θ free moved away from the held θ_n
        assert np.abs(th - sm._end_extensions[-1]._theta).max() > 1e-4 * scale
    d_end = _smooth_end_calibration(s, sm, end)
    d_nowin = _smooth_end_calibration(s, sm, replace(end, disturbances=[]))
    print(f"windows_end={mode}: smooth_fixed(end_calibration) vs stream {d_end:.2e}°, without its windows "
          f"{d_nowin:.4f}°")
    assert d_end < 0.05
    assert d_nowin > 0.05


def test_calibration_json_is_the_end_graph(magnet_window_start_off):
    """calib_json_end_graph with windows_end: StreamSmoother.cal (calibration.json) holds the end θ and the end windows
    (end_calibration), not the causal detector's windows."""
    from imugraph.calibration.result import Calibration
    from imugraph.graphs.stream_windows_end import end_calibration

    s, cal, scale, _, _ = magnet_window_start_off
    rng = np.random.default_rng(0)
    start = replace(cal, D=cal.D + 0.03 * scale * rng.standard_normal((3, 3)),
                    o=cal.o + 0.03 * scale * rng.standard_normal(3))
    sm, _ = _stream(s, start, windows_end="theta", calib_json_end_graph=True)
    want = end_calibration(sm, sm._end_cal)
    assert [d["source"] for d in sm.cal.disturbances] == ["stream_end"]
    assert np.allclose(sm.cal.D, want.D) and np.allclose(sm.cal.o, want.o) and sm.cal.dip_deg == want.dip_deg
    back = Calibration.from_dict(sm.cal.to_dict())            # the JSON round trip keeps the windows
    assert back.disturbances[0]["offset"] == sm.cal.disturbances[0]["offset"]
    d = _smooth_end_calibration(s, sm, back)
    print(f"calibration.json (windows_end='theta') smoothed vs stream {d:.2e}°")
    assert d < 0.05
