"""Issue 3: the stream's smoothed orientation at the end against the batch smoother (`smooth --calibration`,
`imugraph.graphs.cpp_smoother.smooth_fixed`) given the calibration the stream's factors were built with,
and the comparison metric of benchmarks/stream_vs_batch.py.

Without the nav-field perturbation (`field_sigma=None`) the stream's graph is smooth_fixed's, so the only
difference left is the solver and which calibration the magnetometer factors carry:
  * θ as a pinned graph state (`calib_states=True`): every factor keeps the START calibration;
  * the closed-form refit (`calib_states=False`): well-determined refits are swapped into new factors, so the
    result is close to smooth_fixed with the END calibration.
(Simulation, seed 3, 30 s: 0.010° / 0.002°; with the field perturbation on, a model smooth_fixed does not
have, ≈ 0.1° — measured, not asserted here.)
"""

import numpy as np
import pytest

from benchmarks.stream_vs_batch import rms_between
from imugraph.graphs.cpp_smoother import smooth_fixed
from imugraph.graphs.stream import StreamOptions
from imugraph.graphs.stream_run import stream_session
from imugraph.sim.scenario import distorted_session

RATE = 100.0


def _mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p ⊗ q of (N, 4) or (4,) quaternions w,x,y,z, written out (independent of imugraph.geometry)."""
    w1, x1, y1, z1 = np.broadcast_arrays(*np.moveaxis(np.atleast_2d(p), 1, 0))
    w2, x2, y2, z2 = np.moveaxis(np.atleast_2d(q), 1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)


def _axis_angle(angle_rad: np.ndarray, axis) -> np.ndarray:
    """[cos(a/2), sin(a/2) u] per angle."""
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.asarray(angle_rad, float).reshape(-1, 1)
    return np.hstack([np.cos(a / 2), np.sin(a / 2) * u])


def test_rms_between_known_angles():
    """Half the samples 0.1°, half 0.3° apart (about a tilted axis, not heading): RMS √((0.01 + 0.09)/2)°;
    a mask keeps only the 0.3° rows; no heading offset is removed (a pure heading turn counts in full)."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(400, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ang = np.radians(np.where(np.arange(400) < 200, 0.1, 0.3))
    q2 = _mul(q, _axis_angle(ang, [0.3, -1.0, 0.5]))                   # body-side turn
    assert rms_between(q, q2, None, RATE) == pytest.approx(np.sqrt(0.05), rel=1e-6)
    assert rms_between(q, q2, np.arange(400) >= 200, RATE) == pytest.approx(0.3, rel=1e-6)
    q3 = _mul(_axis_angle(np.radians(0.5), [0, 0, 1]), q)                    # nav heading offset 0.5°
    assert rms_between(q, q3, None, RATE) == pytest.approx(0.5, rel=1e-6)
    assert rms_between(q, q3, None, RATE, heading=True) < 1e-6               # ... unless heading is aligned
    assert rms_between(q, _mul(_axis_angle(np.radians(0.5), [0, 0, 1]), q2), np.arange(400) >= 200, RATE,
                       heading=True) == pytest.approx(0.3, rel=1e-3)         # the body-side part stays


@pytest.fixture(scope="module")
def sim():
    session, truth = distorted_session(3, 30.0, RATE)
    return session, truth.to_calibration()


@pytest.mark.parametrize("calib_states", [True, False])
def test_smoothed_matches_batch_with_the_calibration_its_factors_carry(sim, calib_states):
    """Full iSAM2, online calibration on, field perturbation off (smooth_fixed's model): pinned θ → within
    0.1° (the issue's target) of smooth_fixed with the start calibration; refit → of the end calibration."""
    session, cal = sim
    opts = StreamOptions(lag_s=None, field_sigma=None, online_calibration=True, calib_states=calib_states,
                         disturb_detect=calib_states)
    r = stream_session(session, cal, opts)
    assert r.counts["failed_updates"] == 0
    ref_cal = r.start_calibration if calib_states else r.calibration
    q_batch = smooth_fixed(session, ref_cal, keyframe_hz=opts.keyframe_hz, rotation_tol_deg=0.001)
    gap = rms_between(r.smoothed, q_batch, None, RATE)
    assert gap < 0.05, gap


# --- arrival problems on real data, one kind at a time (issue 3: "late, out of order, duplicated, missing, and
# magnetometer samples at a lower rate are handled and counted; none crashes"); tests/test_stream.py injects
# them all at once into a simulation. BROAD 01, 20–35 s (rotation after the initial rest), 286 Hz, the sphere
# calibration of tests/test_stream.py::test_real_broad_updates_all_solve, full iSAM2 (the CLI's default).

KINDS = ("duplicated", "out_of_order", "late", "missing", "mag_quarter_rate", "invalid")


@pytest.fixture(scope="module")
def broad():
    from benchmarks.common import broad_trials, load_broad_trial, trial_number
    from imugraph.calibration.result import Calibration

    paths = [p for p in broad_trials() if trial_number(p) == 1]
    if not paths:
        pytest.skip("BROAD data not present")
    s = load_broad_trial(paths[0])
    s = s.slice(int(20 * s.rate), int(35 * s.rate))
    cal = Calibration(D=44.0 * np.eye(3), o=np.zeros(3), dip_deg=69.0,
                      noise={"gyr": np.full(3, 0.0018), "acc": np.full(3, 0.05), "mag": np.full(3, 0.9)})
    clean = _feed(s, cal, [(i, s.mag[i]) for i in range(s.n)])
    return s, cal, clean


def _feed(s, cal, arrivals, extra=()):
    """Push (row index, mag row or None) in the given order; `extra`: (position, row tuple) pushed before the
    arrival at that position. Returns (stats, smoothed, sample times); every push must return a unit quaternion."""
    from imugraph.graphs.stream import StreamSmoother

    sm = StreamSmoother(cal, s.rate, StreamOptions(lag_s=None, online_calibration=False),
                        g0=float(np.median(np.linalg.norm(s.acc, axis=1))))
    extra = dict(extra)
    for j, (i, mag) in enumerate(arrivals):
        if j in extra:
            sm.push(*extra[j])
        q = sm.push(s.t[i], s.gyr[i], s.acc[i], mag)
        assert q.shape == (4,) and np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-9
    sm.finish()
    return sm.stats, sm.smoothed(), sm.sample_times()


def _vs_clean(clean, smoothed, t_kept, s):
    """RMS angle (°) between a run's smoothed rows and the clean run's at the same time stamps."""
    _, q_clean, t_clean = clean
    idx = np.searchsorted(t_clean, t_kept)
    assert np.allclose(t_clean[idx], t_kept)
    return rms_between(smoothed, q_clean[idx], None, s.rate)


def _truth(q, t_kept, s):
    """RMS error (°) against the optical truth at the kept rows (best heading offset and time shift)."""
    from imugraph.evaluate import orientation_error
    idx = np.searchsorted(s.t, t_kept)
    return orientation_error(q, s.quat[idx], None, s.rate).rms_deg


@pytest.mark.parametrize("kind", KINDS)
def test_real_arrival_problem_counted_and_harmless(broad, kind):
    s, cal, clean = broad
    n, order = s.n, list(range(s.n))
    mags = {i: s.mag[i] for i in range(n)}
    extra = ()
    if kind == "duplicated":                       # every 97th row delivered twice: dropped, result unchanged
        dup = set(range(50, n, 97))
        arrivals = [(i, mags[i]) for i in order for _ in range(2 if i in dup else 1)]
    elif kind == "out_of_order":                   # neighbours swapped: inserted while the interval is open
        swaps = list(range(100, n - 1, 97))
        for p in swaps:
            order[p], order[p + 1] = order[p + 1], order[p]
        arrivals = [(i, mags[i]) for i in order]
    elif kind == "late":                           # a row arriving 100 rows (0.35 s) late: its interval is solved
        late = list(range(300, n - 200, 500))
        for p in late:
            order.remove(p)
            order.insert(order.index(p + 100) + 1, p)
        arrivals = [(i, mags[i]) for i in order]
    elif kind == "missing":                        # 50 rows never arrive
        arrivals = [(i, mags[i]) for i in order if not 2000 <= i < 2050]
    elif kind == "mag_quarter_rate":               # magnetometer at a quarter of the gyro rate
        arrivals = [(i, mags[i] if i % 4 == 0 else None) for i in order]
    else:                                          # rows with a NaN gyro / an infinite accelerometer
        arrivals = [(i, mags[i]) for i in order]
        extra = [(1000, (s.t[999] + 1e-4, [np.nan, 0.0, 0.0], list(s.acc[999]), None)),
                 (3000, (s.t[2999] + 1e-4, list(s.gyr[2999]), [np.inf, 0.0, 0.0], None))]
    st, smoothed, t_kept = _feed(s, cal, arrivals, extra)
    assert st.failed_updates == 0
    gap = _vs_clean(clean, smoothed, t_kept, s)
    if kind == "duplicated":
        assert st.duplicates == len(dup) and st.accepted == n
        assert gap < 1e-9
    elif kind == "out_of_order":
        assert st.late_inserted + st.late_dropped == len(swaps) and st.late_inserted > 0
        assert st.accepted == n - st.late_dropped and gap < 0.05
    elif kind == "late":
        assert st.late_dropped == len(late) and st.accepted == n - len(late)
        assert st.missing == st.gaps == len(late) and gap < 0.2       # as a 1-row gap each (0.050° measured)
    elif kind == "missing":
        # 0.175 s never arrive: the held rate is trusted as the gap model says (factors.gaps eq. G1), so the
        # orientation after the gap leans on this crude calibration's field more than the clean run's does (0.74°
        # from it, measured; 0.08° with the gap model off) — harmless where it counts: against the truth
        assert (st.gaps, st.missing, st.accepted) == (1, 50, n - 50) and gap < 1.0
        assert _truth(smoothed, t_kept, s) < _truth(clean[1], clean[2], s) + 0.2
    elif kind == "mag_quarter_rate":
        assert st.mag_samples == len(range(0, n, 4)) and st.accepted == n
        # 4× fewer field samples: not the clean run's result (0.29° from it, measured), but as accurate
        assert gap < 0.5 and _truth(smoothed, t_kept, s) < _truth(clean[1], clean[2], s) + 0.2
    else:
        assert st.invalid == 2 and st.accepted == n and gap < 1e-9
