"""StreamOptions.mag_delay_end (session 19, helper D): the end graph re-estimates the magnetometer's lag on the whole
stream (imugraph.graphs.stream_delay_end) and re-pairs the rows when the whole-sample shift differs from the
bootstrap's. Known answer: a simulated magnetometer that lags the gyro by exactly LAG samples (its row i holds the field
the body saw at row i − LAG), streamed from the true calibration with a wrong lag."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.graphs.stream_delay_end import fill_short_holes, gyro_rates, move_rows
from imugraph.sim.scenario import distorted_session

from stream_runs import stream_isolated as _stream, truth_rms as _truth_rms

RATE, LAG = 100.0, 3            # Hz; the true lag in samples (30 ms)


@pytest.fixture(scope="module")
def lagged():
    """60 s at 100 Hz, the magnetometer rows moved LAG samples late (the first LAG rows: no sample)."""
    session, truth = distorted_session(7, 60.0, RATE)
    mag = np.full_like(session.mag, np.nan)
    mag[LAG:] = session.mag[:-LAG]
    return session.with_mag(mag), truth.to_calibration()


def test_move_rows():
    rows = np.arange(12, dtype=float).reshape(4, 3)
    assert np.array_equal(move_rows(rows, 1)[:3], rows[1:]) and np.all(np.isnan(move_rows(rows, 1)[3]))
    assert np.array_equal(move_rows(rows, -2)[2:], rows[:2]) and np.all(np.isnan(move_rows(rows, -2)[:2]))
    assert np.array_equal(move_rows(rows, 0), rows)
    assert np.all(np.isnan(move_rows(rows, 5)))


def test_fill_short_holes():
    """Runs of ≤ max_rows NaN rows between valid rows: linear in t; longer runs and runs at either end: NaN."""
    t = np.arange(12, dtype=float)
    m = np.stack([2.0 * t, -t, t * 0 + 1.0], 1)
    holes = m.copy()
    holes[[0, 3, 4, 7, 8, 9, 11]] = np.nan           # edge, a run of 2, a run of 3, edge
    out = fill_short_holes(t, holes, 2)
    assert np.allclose(out[3:5], m[3:5])
    assert np.all(np.isnan(out[[0, 7, 8, 9, 11]]))
    assert np.allclose(fill_short_holes(t, holes, 3)[7:10], m[7:10])
    assert np.array_equal(fill_short_holes(t, holes, 0), holes, equal_nan=True)


def test_gyro_rates_recover_the_pushed_rates(lagged):
    """Eq. (1): the rates recovered from the history equal (gyro − b̂) of the pushed rows (E = 0 here)."""
    s, cal = lagged
    sm, _ = _stream(s, replace(cal, mag_delay_s=LAG / RATE), mag_delay_end=True)
    t, w = gyro_rates(sm._hist_kRb, sm._hist_dR, sm._hist_t, float(sm._kf_t[len(sm._hist_t)]))
    n = len(t)
    assert np.allclose(t, s.t[:n])
    assert np.abs(w - (s.gyr[:n] - np.asarray(cal.gyro_bias))).max() < 1e-9


@pytest.mark.parametrize("mode", [True, "clean"])
def test_wrong_start_lag_is_corrected(lagged, mode):
    """Start lag 1 sample (2 short): the end graph finds 3, re-pairs, its smoothed error against the truth drops, and
    calibration.json carries the new lag; the filtered output is untouched."""
    s, cal = lagged
    start = replace(cal, mag_delay_s=1.0 / RATE)
    off, q_off = _stream(s, start, mag_delay_end=False)
    on, q_on = _stream(s, start, mag_delay_end=mode)
    info = on._delay_end.info
    err_off, err_on = _truth_rms(off.smoothed(), s), _truth_rms(on.smoothed(), s)
    print(f"lag {info}; smoothed vs truth {err_off:.3f} → {err_on:.3f}°")
    assert np.array_equal(q_off, q_on)
    assert info["applied"] and info["shift_start"] == 1 and info["shift_end"] == LAG
    assert abs(info["tau_s"] - LAG / RATE) < 0.5 / RATE
    assert err_on < 0.8 * err_off
    assert abs(on.cal.mag_delay_s - info["tau_s"]) < 1e-12 and off.cal.mag_delay_s == start.mag_delay_s
    # the history holds the re-paired rows: row i of the stream now holds the field sensed at row i
    y = np.concatenate(on._hist_y)
    n = len(y) - LAG
    ok = np.all(np.isfinite(y[:n]), axis=1)
    assert ok.mean() > 0.85 and np.array_equal(y[:n][ok], s.mag[LAG:LAG + n][ok])


def test_same_shift_leaves_the_output_identical(lagged):
    """Start lag right (3 samples): the estimate rounds to the same shift, and the smoothed output is bit for bit the
    option-off one."""
    s, cal = lagged
    start = replace(cal, mag_delay_s=LAG / RATE)
    off, _ = _stream(s, start, mag_delay_end=False)
    on, _ = _stream(s, start, mag_delay_end=True)
    assert on._delay_end.info["shift_end"] == LAG and not on._delay_end.info["applied"]
    assert np.array_equal(off.smoothed(), on.smoothed())
    assert on.cal.mag_delay_s == start.mag_delay_s


def test_guarded_keeps_the_corrected_shift(lagged):
    """mag_delay_end="guarded" (helper G): start lag 2 samples short, the end graph's total cost (eq. 3) is lower with
    the re-paired rows, so they are kept as with True (same shift, same re-paired rows)."""
    s, cal = lagged
    start = replace(cal, mag_delay_s=1.0 / RATE)
    off, _ = _stream(s, start, mag_delay_end=False)
    on, _ = _stream(s, start, mag_delay_end="guarded")
    info = on._delay_end.info
    print(info)
    assert info["applied"] and info["shift_start"] == 1 and info["shift_end"] == LAG
    assert info["guard_cost_s1"] < info["guard_cost_s0"]
    assert _truth_rms(on.smoothed(), s) < 0.8 * _truth_rms(off.smoothed(), s)
    assert abs(on.cal.mag_delay_s - info["tau_s"]) < 1e-12


def test_guarded_keeps_shift_zero_when_a_magnet_comes_off():
    """A magnet attached at the start comes off at 14 s (true lag 0, 50 Hz): τ̂ reads −12.7 ms and True re-pairs the
    rows by −1 (smoothed error 0.17 → 1.09°, benchmarks/d19_magnet_off.py); "guarded" solves both end graphs, keeps
    the stream's pairing, and its smoothed error stays within 0.05° of the option off (the final LM starts at s₀'s
    optimum instead of iSAM2's estimate)."""
    from benchmarks.stream_vs_batch import stream_with_recorder
    from imugraph.graphs.stream import StreamOptions
    from imugraph.sim.scenario import magnet_comes_off_session

    s, start, _ = magnet_comes_off_session()
    errs, infos = {}, {}
    for mode in (False, "guarded"):                 # as benchmarks/d19_magnet_off.py: every default, 10 s bootstrap
        r, sm = stream_with_recorder(s, StreamOptions(lag_s=None, mag_delay_end=mode), 10.0, start, 0)
        errs[mode] = _truth_rms(r.smoothed, s)
        infos[mode] = getattr(sm, "_delay_end", None)
    info = infos["guarded"].info
    print(info, errs)
    assert info["shift_start"] == 0 and info["shift_end"] != 0            # the biased estimate (the case guarded)
    assert not info["applied"] and info["guard_cost_s0"] < info["guard_cost_s1"]
    assert infos["guarded"].tau_s is None
    assert abs(errs["guarded"] - errs[False]) < 0.05
