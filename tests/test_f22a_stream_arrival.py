"""Session 22, helper F22a: the stream's arrival fixes (U22 defects 2 and 10).

Defect 2: with a lagging magnetometer (cal.mag_delay_s > 0, every BROAD calibration) a late sample was always dropped,
though graphs/stream.py says it is inserted while its keyframe interval is open. Known answer: neighbours swapped
inside an interval, once inserted with the field re-paired (stream_interval.ArrivalMixin._insert_shifted), leave the
open interval exactly as the in-order stream has it, so the smoothed output is the in-order one, bit for bit.

Defect 10: wrong argument types and shapes raise SessionError naming the field; a nominal rate the time stamps
contradict warns once (rate=1000 on 100 Hz data: every step looked like a gap, no word said).
"""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.errors import SessionError
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.sim.scenario import distorted_session

RATE, SHIFT = 100.0, 3          # Hz; the magnetometer lag in samples (30 ms)
STRIDE = 10                     # samples per keyframe at the default keyframe_hz 10


@pytest.fixture(scope="module")
def lagged():
    """40 s at 100 Hz from the true calibration with a 3-sample magnetometer lag (the stream shifts the field by it)."""
    session, truth = distorted_session(11, 40.0, RATE)
    return session, replace(truth.to_calibration(), mag_delay_s=SHIFT / RATE)


def _run(session, cal, order, **opt):
    sm = StreamSmoother(cal, RATE, StreamOptions(**{"lag_s": 2.0, **opt}),
                        g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
    for i in order:
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    sm.finish()
    return sm


def _swapped(n: int, positions) -> list:
    order = list(range(n))
    for p in positions:
        order[p], order[p + 1] = order[p + 1], order[p]
    return order


def test_late_samples_inserted_with_a_lagging_magnetometer(lagged):
    """Swaps inside an interval (rows 2..8 of 10, so the successor never closes it): all inserted, none dropped, and
    the smoothed output and calibration equal the in-order stream's. Fails before the fix: 0 inserted, all dropped."""
    s, cal = lagged
    swaps = [p for p in range(40, s.n - 2, 37) if 2 <= p % STRIDE <= 7]
    ref = _run(s, cal, range(s.n))
    sm = _run(s, cal, _swapped(s.n, swaps))
    c = sm.stats
    assert (c.late_inserted, c.late_dropped, c.gaps) == (len(swaps), 0, 0)
    assert c.mag_dropped == ref.stats.mag_dropped and c.mag_samples == ref.stats.mag_samples
    assert np.array_equal(sm.sample_times(), ref.sample_times())
    assert np.array_equal(sm.smoothed(), ref.smoothed())
    assert np.array_equal(sm.cal.D, ref.cal.D) and np.array_equal(sm.cal.o, ref.cal.o)


def test_late_sample_re_pairs_the_fields_across_the_head(lagged):
    """A swap within the first SHIFT rows of an interval: the fields that belong to the closed interval (the head) are
    re-paired too — the open buffer after the insertion equals the in-order one (fields included)."""
    s, cal = lagged
    for p in (STRIDE * 7 + 1, STRIDE * 7 + 2, STRIDE * 7 + 3, STRIDE * 7 + 5):
        end = p + 3
        a = StreamSmoother(cal, RATE, StreamOptions(lag_s=2.0))
        b = StreamSmoother(cal, RATE, StreamOptions(lag_s=2.0))
        for sm, order in ((a, range(end)), (b, _swapped(end, [p]))):
            for i in order:
                sm.push(s.t[i], s.gyr[i], s.acc[i], s.mag[i])
        assert b.stats.late_inserted == 1 and b.stats.mag_dropped == a.stats.mag_dropped
        assert np.array_equal(np.array(b._buf), np.array(a._buf), equal_nan=True)
        assert b._q_open == a._q_open


def test_sample_overtaken_across_a_keyframe_is_still_dropped(lagged):
    """The successor that starts a new interval closes the old one: the late row is dropped (as without a lag)."""
    s, cal = lagged
    p = STRIDE * 5        # row 50 (keyframe 5 in order) overtaken by row 51, which closes interval 4 (rows 40–49)
    sm = _run(s, cal, _swapped(200, [p]))
    assert (sm.stats.late_inserted, sm.stats.late_dropped) == (0, 1)


@pytest.mark.parametrize("rate", ["100", None, True, float("nan"), -1.0, [100.0]])
def test_bad_rate_is_a_session_error(lagged, rate):
    with pytest.raises(SessionError, match="field 'rate'"):
        StreamSmoother(lagged[1], rate)


@pytest.mark.parametrize("field, args", [("gyr", (0.0, [0.0, 0.0], [0, 0, 9.8])),
                                         ("acc", (0.0, [0.0, 0.0, 0.0], [0, 9.8])),
                                         ("mag", (0.0, [0.0, 0.0, 0.0], [0, 0, 9.8], [1.0, 2.0])),
                                         ("gyr", (0.0, "abc", [0, 0, 9.8])),
                                         ("t", ("noon", [0.0, 0.0, 0.0], [0, 0, 9.8]))])
def test_bad_push_arguments_are_session_errors(lagged, field, args):
    sm = StreamSmoother(lagged[1], RATE)
    with pytest.raises(SessionError, match=f"field '{field}'"):
        sm.push(*args)
    assert sm.stats.accepted == 0


def test_nominal_rate_contradicted_by_the_time_stamps_warns_once(lagged):
    """rate=1000 (and 30) on 100 Hz data: one RuntimeWarning naming the arriving rate; the right rate: none."""
    s, cal = lagged
    for rate, warns in ((1000.0, True), (30.0, True), (RATE, False), (RATE * 1.2, False)):
        sm = StreamSmoother(cal, rate, StreamOptions(lag_s=2.0))
        with pytest.warns(RuntimeWarning) if warns else _no_warning() as rec:
            for i in range(600):
                sm.push(s.t[i], s.gyr[i], s.acc[i], s.mag[i])
        if warns:
            assert len([w for w in rec if issubclass(w.category, RuntimeWarning)]) == 1
            assert "100 Hz" in str(rec[0].message) and "field 'rate'" in str(rec[0].message)
        assert abs(sm.rate_ratio - rate / RATE) < 1e-6


class _no_warning:
    def __enter__(self):
        import warnings
        self._cm = warnings.catch_warnings()
        self._cm.__enter__()
        warnings.simplefilter("error", RuntimeWarning)
        return []

    def __exit__(self, *exc):
        return self._cm.__exit__(*exc)


# ---------------------------------------------------------------- the "Also": StreamOptions.mag_carry (stream_carry)
@pytest.fixture(scope="module")
def truly_lagged():
    """60 s at 100 Hz whose magnetometer row i holds the field the body saw at row i − SHIFT (as test_stream_delay_end),
    and the true calibration with that lag."""
    session, truth = distorted_session(7, 60.0, RATE)
    mag = np.full_like(session.mag, np.nan)
    mag[SHIFT:] = session.mag[:-SHIFT]
    return session, session.with_mag(mag), replace(truth.to_calibration(), mag_delay_s=SHIFT / RATE)


def _iSAM2(session, cal, **opt):
    from stream_runs import stream_isolated
    return stream_isolated(session, cal, **opt)[0]


def test_mag_carry_keeps_every_field_sample(truly_lagged):
    """Without mag_carry each interval's last SHIFT rows lose their field (mag_dropped = SHIFT per interval); with it
    none is lost, and the kept rows hold, row for row, the field the body saw there (the un-lagged rows)."""
    clean, s, cal = truly_lagged
    off, on = _iSAM2(s, cal), _iSAM2(s, cal, mag_carry=True)
    n_int = len(off._hist_y)
    assert off.stats.mag_dropped == SHIFT * (n_int - 1) and on.stats.mag_dropped == 0   # first rows: no field here
    y_off, y_on = np.concatenate(off._hist_y), np.concatenate(on._hist_y)
    n = len(y_on) - SHIFT                        # the last SHIFT fields never arrive
    assert np.isnan(y_off[:n, 0]).sum() >= SHIFT * (n_int - 1)
    assert np.array_equal(y_on[:n], clean.mag[:n])


def test_mag_carry_off_is_the_default_and_changes_nothing(truly_lagged):
    _, s, cal = truly_lagged
    assert StreamOptions().mag_carry is False
    a, b = _iSAM2(s, cal), _iSAM2(s, cal, mag_carry=False)
    assert np.array_equal(a.smoothed(), b.smoothed())
