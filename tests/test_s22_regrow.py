"""stream_session(bootstrap_regrow=…) (helper S22): a stream started from a weak (not identifiable) calibration keeps
growing its bootstrap while streaming and switches to the first window that identifies D, o (stream_run.push_regrow).

Checked on a simulation (distorted_session, 40 s, 100 Hz) with calibrate replaced by a stub that identifies the
true calibration only on windows of at least 15 s: the output before the switch is the no-regrow stream's bit for
bit (nothing from the future), after it that of a stream started with the identified window's calibration (the
replay), the calibration saw only rows that had arrived before the switch, and the error after the switch drops."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.evaluate import orientation_error
from imugraph.graphs.stream import StreamOptions
from imugraph.graphs.stream_run import stream_session
from imugraph.sim.scenario import distorted_session

OPT = StreamOptions(lag_s=2.0)


@pytest.fixture(scope="module")
def sim():
    session, truth = distorted_session(5, 40.0, 100.0)
    good = truth.to_calibration()
    s = float(np.cbrt(abs(np.linalg.det(good.D))))
    weak = replace(good, D=s * np.eye(3), o=np.zeros(3),
                   coverage={"identifiable": False, "problems": ["too little rotation (test)"]})
    return session, good, weak


@pytest.fixture()
def stub(sim, monkeypatch):
    """calibrate: the true calibration on windows ≥ 15 s, else CalibrationError (what the coverage check raises)."""
    from imugraph.calibration import ml
    from imugraph.errors import CalibrationError

    _, good, _ = sim
    seen = []

    class Est:
        def __init__(self, cal):
            self.calibration, self.info = cal, {}

    def fake(sub, options=None, allow_weak=False):
        seen.append((sub.n, float(sub.t[-1] - sub.t[0])))
        if sub.t[-1] - sub.t[0] < 15.0:
            raise CalibrationError("too little rotation to calibrate (test stub)")
        return Est(good)

    monkeypatch.setattr(ml, "calibrate", fake)
    return seen


def test_regrow_switches_causally_and_recovers(sim, stub):
    session, good, weak = sim
    n10 = int(np.searchsorted(session.t, session.t[0] + 10.0, side="right"))
    off = stream_session(session, None, OPT, 10.0, bootstrap=(weak, n10))
    on = stream_session(session, None, OPT, 10.0, bootstrap=(weak, n10), bootstrap_regrow=True)
    log = on.timing["regrow"]
    assert [e["identified"] for e in log] == [True] and log[0]["switched_t"] is not None
    n15, t_sw = log[0]["rows"], log[0]["switched_t"]
    assert stub == [(n15, log[0]["span_s"])] and log[0]["span_s"] <= t_sw       # only rows already arrived
    i_sw = int(np.searchsorted(session.t, session.t[0] + t_sw))
    assert n15 <= i_sw < session.n
    # before the switch: the no-regrow stream bit for bit
    np.testing.assert_array_equal(on.filtered[:i_sw], off.filtered[:i_sw])
    # after it: a stream started with the identified window's calibration, fed every row
    ref = stream_session(session, None, OPT, 10.0, bootstrap=(good, n15))
    np.testing.assert_array_equal(on.filtered[i_sw:], ref.filtered[i_sw:])
    # and it recovers: the filtered error after the switch is below the weak start's
    late = np.arange(session.n) >= i_sw + int(2 * session.rate)
    e_on = orientation_error(on.filtered, session.quat, late, session.rate).rms_deg
    e_off = orientation_error(off.filtered, session.quat, late, session.rate).rms_deg
    assert e_on < e_off


def test_regrow_leaves_an_identified_start_alone(sim, stub):
    """An identifiable start (or a given calibration): no window is tried, the output is the default's."""
    session, good, _ = sim
    part = session.slice(0, int(20 * session.rate))
    n10 = int(np.searchsorted(part.t, part.t[0] + 10.0, side="right"))
    a = stream_session(part, None, OPT, 10.0, bootstrap=(good, n10))
    b = stream_session(part, None, OPT, 10.0, bootstrap=(good, n10), bootstrap_regrow=True)
    assert stub == [] and "regrow" not in b.timing
    np.testing.assert_array_equal(a.filtered, b.filtered)


def test_weak_centre(sim):
    """weak_centre: a non-identifiable calibration → D = s·I, o = 0 with s the median |y| of the first n rows' fields
    (computed here with numpy); an identifiable one is returned as is; the stream runs with it."""
    from imugraph.graphs.stream_run import weak_centre

    session, good, weak = sim
    n = int(5 * session.rate)
    y = session.mag[:n][np.all(np.isfinite(session.mag[:n]), axis=1)]
    s = np.median(np.sqrt((y ** 2).sum(axis=1)))
    c = weak_centre(weak, session, n)
    np.testing.assert_allclose(c.D, s * np.eye(3), rtol=1e-12)
    assert np.all(c.o == 0.0) and c.dip_deg == weak.dip_deg and not np.allclose(weak.D, c.D)
    assert weak_centre(good, session, n) is good
    part = session.slice(0, int(12 * session.rate))
    r = stream_session(part, None, OPT, 5.0, bootstrap=(weak, n), bootstrap_weak_centre=True)
    assert np.allclose(r.start_calibration.D, c.D) and np.all(np.isfinite(r.filtered))      # what it streamed with


def test_regrow_align_turns_about_the_vertical_only(sim, stub):
    """regrow_align (eq. R2): before the switch the output is unchanged; after it, the new smoother's output turned by one
    constant rotation about nav z, chosen so that the output does not jump in heading at the switch."""
    from imugraph.geometry import quat_angle, quat_conj, quat_mul

    session, good, weak = sim
    n10 = int(np.searchsorted(session.t, session.t[0] + 10.0, side="right"))
    raw = stream_session(session, None, OPT, 10.0, bootstrap=(weak, n10), bootstrap_regrow=True)
    al = stream_session(session, None, OPT, 10.0, bootstrap=(weak, n10), bootstrap_regrow=True, regrow_align=True)
    i_raw = int(np.searchsorted(session.t, session.t[0] + raw.timing["regrow"][0]["switched_t"]))
    i_sw = int(np.searchsorted(session.t, session.t[0] + al.timing["regrow"][0]["switched_t"]))
    i = max(i_raw, i_sw)                       # the switch row follows the CPU time (R1): compare after both
    np.testing.assert_array_equal(al.filtered[:min(i_raw, i_sw)], raw.filtered[:min(i_raw, i_sw)])
    rel = quat_mul(al.filtered[i:], quat_conj(raw.filtered[i:]))
    rel *= np.sign(rel[:, :1])
    assert np.max(np.abs(rel[:, 1:3])) < 1e-9 and np.ptp(rel[:, 3]) < 1e-9
    jump_al = quat_angle(al.filtered[i_sw], al.filtered[i_sw - 1])
    jump_raw = quat_angle(raw.filtered[i_raw], raw.filtered[i_raw - 1])
    assert jump_al <= jump_raw + 1e-6
