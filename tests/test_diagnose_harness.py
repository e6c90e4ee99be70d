"""The diagnosis' validation harness (imugraph.diagnose.harness): bookkeeping with a stub diagnoser, and
a small blind run of the real diagnoser (one simulated and one BROAD case; the BROAD one skips without
the data)."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import broad_sessions, simulated_session
from imugraph.diagnose.harness import format_report, run_harness


def test_harness_bookkeeping_with_stub_diagnoser():
    sessions = [simulated_session(0, 15.0, 50.0)]
    seen = []

    def stub(session):
        seen.append(session)
        # a diagnoser that always answers "vibration" over [2, 6] s with shrink 0.9
        return {"verdict": "vibration", "gap": {}, "effects": [
            {"name": "vibration", "t_start": 2.0, "t_end": 6.0, "shrink": 0.9}]}

    rep = run_harness(sessions, ["vibration", "accelerometer_bias"], 2, np.random.default_rng(0),
                      diagnose_fn=stub)
    assert rep["n_injected"] == 4 and rep["n_clean"] == 1
    assert rep["confusion"]["vibration"]["vibration"] == 2
    assert rep["confusion"]["accelerometer_bias"]["vibration"] == 2
    assert rep["top1"] == pytest.approx(0.5) and rep["clean_flagged"] == 1
    assert rep["iou"]["n"] == 2 and all(0.0 <= c["iou"] <= 1.0 for c in rep["cases"] if c["iou"] is not None)
    assert rep["shrink"]["median"] == pytest.approx(0.9)
    for s in seen:                                  # the label is hidden from the diagnoser
        assert "vibration" not in s.name and "accelerometer" not in s.name and "injected" not in s.meta
    text = format_report(rep)
    assert "confusion matrix" in text and "top-1: 50 %" in text


def test_harness_small_blind_run_on_simulation():
    pytest.importorskip("imugraph.diagnose.run")
    rep = run_harness([simulated_session(7, 30.0, 100.0)], ["vibration"], 1, np.random.default_rng(3),
                      clean=False)
    case = rep["cases"][0]
    assert case["verdict"] == "vibration", case
    assert case["iou"] is not None and case["iou"] > 0.7


def test_harness_small_blind_run_on_broad(data_dir):
    pytest.importorskip("imugraph.diagnose.run")
    sessions = broad_sessions(["01"], 20.0, str(data_dir))
    if not sessions:
        pytest.skip("BROAD trial 01 is absent")
    rep = run_harness(sessions, ["linear_acceleration"], 1, np.random.default_rng(1), clean=False)
    assert rep["cases"][0]["verdict"] == "linear_acceleration", rep["cases"][0]


def test_crop_takes_the_most_moving_stretch():
    """most_moving: a session at rest for its first 20 s and turning over the next 10 s is cropped to a
    stretch that holds the turning (known answer: the 8 s crop lies inside 20–30 s)."""
    from imugraph.diagnose.bench import most_moving
    from imugraph.io.session import Session

    rate = 50.0
    t = np.arange(0, 40.0, 1 / rate)
    gyr = np.zeros((len(t), 3)) + 0.01
    gyr[(t >= 20) & (t < 30), 2] = 2.0
    acc = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    mag = np.tile([20.0, 0.0, -40.0], (len(t), 1))
    s = Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=None, movement=None, source="<test>", name="rest_then_turn")
    i0, i1 = most_moving(s, 8.0)
    assert 20.0 - 1e-9 <= t[i0] and t[i1 - 1] < 30.0
    assert t[i1 - 1] - t[i0] == pytest.approx(8.0, abs=2 / rate)


def test_hosts_are_drawn_per_case_from_the_seed():
    """hosts="random": the injected cases' hosts are drawn from the seed (every host of 3 used over 12
    cases, the same draw for the same seed, another for another seed); "cycle" keeps the fixed order."""
    from imugraph.io.session import Session

    def make(name):
        t = np.arange(0, 6.0, 0.02)
        return Session(t=t, gyr=np.zeros((len(t), 3)), acc=np.tile([0.0, 0.0, 9.81], (len(t), 1)),
                       mag=np.tile([20.0, 0.0, -40.0], (len(t), 1)), quat=None, movement=None,
                       source="<test>", name=name)

    sessions = [make("h0"), make("h1"), make("h2")]
    stub = lambda s: {"verdict": "none", "gap": {}, "effects": []}          # noqa: E731

    def hosts(seed, mode="random"):
        rep = run_harness(sessions, ["accelerometer_bias"], 12, np.random.default_rng(seed), clean=False,
                          diagnose_fn=stub, hosts=mode)
        return [c["host"] for c in rep["cases"]]

    a = hosts(5)
    assert set(a) == {"h0", "h1", "h2"} and a == hosts(5) and a != hosts(6)
    assert hosts(5, "cycle") == ["h0", "h1", "h2"] * 4
    with pytest.raises(Exception):
        hosts(5, "sometimes")
