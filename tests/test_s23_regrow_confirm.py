"""Helper S23: the regrow's consistency guard (`regrow_confirm`, stream_regrow eqs. C1, C2), its live-latency
bookkeeping (`live_stats`) and `imugraph stream --bootstrap-regrow`.

The guard's scenario is BROAD 32's (a magnet for most of the first window that identifies): on a simulation
(distorted_session, 40 s, 100 Hz) a stubbed calibrate returns a wrong calibration A (hard iron off by 0.3 of the
field) on the 15-s window and the true one B on windows ≥ 22.5 s. Without the guard the stream stops at A; with it
the 22.5-s window differs from A (beyond its std and in field direction) and is switched to, and the output after
that switch is a stream started with B bit for bit. Known answers for C1 and C2 are computed by hand."""

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.graphs.stream import StreamOptions
from imugraph.graphs.stream_regrow import field_direction_change, live_stats, regrow_consistent
from imugraph.graphs.stream_run import stream_session
from imugraph.sim.scenario import distorted_session

OPT = StreamOptions(lag_s=2.0)
STD = {"D": np.full((3, 3), 0.01), "o": np.full(3, 0.01), "dip_deg": 0.1}


@pytest.fixture(scope="module")
def sim():
    session, truth = distorted_session(5, 40.0, 100.0)
    good = replace(truth.to_calibration(), std=STD)
    s = float(np.cbrt(abs(np.linalg.det(good.D))))
    wrong = replace(good, o=good.o + np.array([0.3 * s, 0.0, 0.0]))
    weak = replace(good, D=s * np.eye(3), o=np.zeros(3), std={},
                   coverage={"identifiable": False, "problems": ["too little rotation (test)"]})
    return session, good, wrong, weak


@pytest.fixture()
def stub(sim, monkeypatch):
    """calibrate: CalibrationError below 15 s, the wrong calibration on [15, 22.5) s, the true one from 22.5 s."""
    from imugraph.calibration import ml
    from imugraph.errors import CalibrationError

    _, good, wrong, _ = sim
    seen = []

    def fake(sub, options=None, allow_weak=False):
        span = float(sub.t[-1] - sub.t[0])
        seen.append(span)
        if span < 14.9:
            raise CalibrationError("too little rotation to calibrate (test stub)")
        return SimpleNamespace(calibration=wrong if span < 22.4 else good, info={})

    monkeypatch.setattr(ml, "calibrate", fake)
    return seen


def test_consistency_known_answers(sim):
    _, good, _, _ = sim
    # (C1): one D entry off by 0.03 with σ 0.01 on both sides → z = 0.03 / sqrt(2e-4) = 2.1213
    other = replace(good, D=good.D + np.diag([0.03, 0.0, 0.0]))
    assert regrow_consistent(good, other) == pytest.approx(0.03 / np.sqrt(2e-4), rel=1e-9)
    assert regrow_consistent(good, replace(other, std={})) == float("inf")
    # (C2): D = I, o = 0 against o = (0, −tan 10°, 0) on the sample y = (1, 0, 0): the directions differ by 10°
    a = replace(good, D=np.eye(3), o=np.zeros(3))
    b = replace(a, o=np.array([0.0, -np.tan(np.radians(10.0)), 0.0]))
    assert field_direction_change(a, b, np.array([[1.0, 0.0, 0.0]]), stride=1) == pytest.approx(10.0, abs=1e-9)
    # a common scale of D turns no direction; NaN rows are skipped
    y = np.array([[0.3, -0.2, 0.9], [np.nan, 0.0, 0.0], [-0.5, 0.4, 0.1]])
    assert field_direction_change(a, replace(a, D=1.07 * np.eye(3)), y, stride=1) < 1e-6


def test_live_stats_leave_out_the_replays():
    """Each smoother's entries from its live start on, in order (the replay + catch-up before it left out)."""
    from array import array

    def sm(u, b):
        return SimpleNamespace(stats=SimpleNamespace(update_s=array("d", u), update_cpu_s=array("d", [x / 2 for x in u]),
                                                     between_s=array("d", b), between_cpu_s=array("d", b)))
    live = live_stats([(sm([1, 2, 3], [7]), (0, 0)), (sm([10, 11, 12, 13, 4], [8, 9, 5]), (4, 2))])
    assert live["update_s"] == [1, 2, 3, 4] and live["update_cpu_s"] == [0.5, 1, 1.5, 2]
    assert live["between_s"] == [7, 5] and live["between_cpu_s"] == [7, 5]


def test_guard_switches_away_from_a_wrong_identified_window(sim, stub):
    session, good, wrong, weak = sim
    n10 = int(np.searchsorted(session.t, session.t[0] + 10.0, side="right"))
    kw = dict(bootstrap=(weak, n10), bootstrap_regrow=True, regrow_latency_s=0.5)
    plain = stream_session(session, None, OPT, 10.0, **kw)
    assert [e["kind"] for e in plain.timing["regrow"]] == ["identified"]          # stops at the wrong window A
    assert np.allclose(plain.timing["regrow"][0]["o"], wrong.o)
    guard = stream_session(session, None, OPT, 10.0, regrow_confirm=2.0, **kw)
    log = guard.timing["regrow"]
    assert [e["kind"] for e in log] == ["identified", "identified", "identified"]      # 15, 22.5, 33.75 s
    assert log[1]["decision"].startswith("differs") and log[1]["z_max"] > 3 and log[1]["dir_deg"] > 0.5
    assert log[2]["decision"] == "consistent, not yet confirmed" and log[2]["switched_t"] is None
    assert np.allclose(log[1]["o"], good.o) and log[1]["span_s"] <= log[1]["switched_t"]
    assert max(stub) < 40.0 and all(e["span_s"] < e["switched_t"] for e in log if e["switched_t"] is not None)
    # before the second switch: the unguarded stream bit for bit; after it: a stream started with B
    i_sw = int(np.searchsorted(session.t, session.t[0] + log[1]["switched_t"]))
    np.testing.assert_array_equal(guard.filtered[:i_sw], plain.filtered[:i_sw])
    ref = stream_session(session, None, OPT, 10.0, bootstrap=(good, log[1]["rows"]))
    np.testing.assert_array_equal(guard.filtered[i_sw:], ref.filtered[i_sw:])
    late = np.arange(session.n) >= i_sw + int(2 * session.rate)
    from imugraph.evaluate import orientation_error
    assert (orientation_error(guard.smoothed, session.quat, late, session.rate).rms_deg
            < orientation_error(plain.smoothed, session.quat, late, session.rate).rms_deg)


def test_cli_bootstrap_regrow(tmp_path, capsys):
    """`imugraph stream --bootstrap-regrow` on a simulated session whose first 3 s and 4.5 s hold too little rotation
    (tests/test_f22a_stream_bootstrap.py): it streams from the 3-s weak start, timing.json lists the windows, each
    switch after its window's last row; the default run has no regrow entry and a grown bootstrap; the filtered
    output after the first identified switch is better than the capped stream's without the regrow."""
    from imugraph.cli import main
    from imugraph.evaluate import orientation_error

    s, _ = distorted_session(3, 40.0, 50.0)
    path = tmp_path / "s.npz"
    np.savez(path, t=s.t, gyr=s.gyr, acc=s.acc, mag=s.mag)
    base = ["stream", str(path), "--bootstrap-s", "3", "--lag", "2"]
    assert main(base + ["--out", str(tmp_path / "re"), "--bootstrap-regrow", "--bootstrap-regrow-latency", "0.5"]) == 0
    err = capsys.readouterr().err
    timing = json.loads((tmp_path / "re" / "timing.json").read_text())
    assert timing["bootstrap_span_s"] <= 3.0 and "capped at bootstrap_max_s = 3 s" in timing["bootstrap_note"]
    log = timing["regrow"]
    assert log and "bootstrap regrow on the first" in err and timing["regrow_cpu_seconds"] >= 0
    sw = [e for e in log if e["switched_t"] is not None]
    assert sw and all(e["switched_t"] >= e["span_s"] + 0.5 - 0.05 for e in sw)
    assert {e["kind"] for e in log} <= {"identified", "weak", "refused"}
    first = next(e for e in sw if e["kind"] == "identified")
    assert main(base + ["--out", str(tmp_path / "cap"), "--bootstrap-max-s", "3"]) == 0
    assert main(base + ["--out", str(tmp_path / "def")]) == 0
    assert "regrow" not in json.loads((tmp_path / "def" / "timing.json").read_text())
    late = s.t >= s.t[0] + first["switched_t"] + 2.0
    err_of = {k: orientation_error(np.load(tmp_path / k / "orientation_filtered.npz")["quat"], s.quat, late, s.rate).rms_deg
              for k in ("re", "cap")}
    assert err_of["re"] < err_of["cap"]
