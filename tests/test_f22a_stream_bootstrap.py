"""Session 22, helper F22a: the stream's bootstrap says what it used, and can be capped (U22 defect 3).

`imugraph stream` printed "bootstrap calibration on the first 30 s" while the bootstrap window grew to the whole
recording (BROAD 16: 186.9 s; too little rotation in 30 s), so the "filtered (causal)" output was a replay there.
Now the progress line and timing.json say the span actually used and why it grew; `bootstrap_max_s` (library) caps
the growth (at the cap: calibrate's weak fallback). Known answer: a simulated session starting with a 2 s rest, whose
first 3 s and 4.5 s hold too little rotation; windows grow 3 → 4.5 → 6.75 s (grow 1.5).
"""

import json

import numpy as np
import pytest

from imugraph.cli import main
from imugraph.errors import SessionError
from imugraph.graphs.stream import StreamOptions
from imugraph.graphs.stream_run import bootstrap_calibration, stream_session
from imugraph.sim.scenario import distorted_session

BOOT_S = 3.0


@pytest.fixture(scope="module")
def session():
    s, _ = distorted_session(3, 40.0, 50.0)
    return s


def _rows_within(s, span: float) -> int:
    return int(np.sum(s.t <= s.t[0] + span))


def test_growth_is_reported(session):
    info = {}
    _, n = bootstrap_calibration(session, BOOT_S, info=info)
    assert n == _rows_within(session, BOOT_S * 1.5 ** 2)
    assert [r for _, r in info["bootstrap_growth"]] == ["too little rotation"] * 2 and not info["bootstrap_capped"]


def test_cap_stops_the_growth(session):
    """max_s = 4 s: the second window is 4 s (not 4.5) and is accepted, whatever calibrate says (weak fallback)."""
    info = {}
    _, n = bootstrap_calibration(session, BOOT_S, info=info, max_s=4.0)
    assert n == _rows_within(session, 4.0) and info["bootstrap_capped"]
    _, n0 = bootstrap_calibration(session, BOOT_S, max_s=None)
    assert n0 > n
    for bad in (0.0, -1.0, float("nan"), "30"):
        with pytest.raises(SessionError, match="bootstrap_max_s"):
            bootstrap_calibration(session, BOOT_S, max_s=bad)


def test_stream_session_says_the_span(session):
    said = []
    r = stream_session(session, None, StreamOptions(lag_s=2.0), bootstrap_s=BOOT_S, say=said.append)
    span = float(session.t[r.bootstrap_samples - 1] - session.t[0])
    assert r.bootstrap_samples == _rows_within(session, BOOT_S * 1.5 ** 2)
    assert r.timing["bootstrap_span_s"] == span
    line = next(m for m in said if m.startswith("bootstrap calibration on"))
    assert line.startswith(f"bootstrap calibration on the first {span:.1f} s (grown from 3 s: too little rotation")
    capped = stream_session(session, None, StreamOptions(lag_s=2.0), bootstrap_s=BOOT_S, bootstrap_max_s=4.0)
    assert capped.bootstrap_samples == _rows_within(session, 4.0)
    assert "capped at bootstrap_max_s = 4 s" in capped.timing["bootstrap_note"]


def test_cli_progress_line_and_timing_json(tmp_path, capsys, session):
    path = tmp_path / "s.npz"
    np.savez(path, t=session.t, gyr=session.gyr, acc=session.acc, mag=session.mag)
    out = tmp_path / "out"
    assert main(["stream", str(path), "--out", str(out), "--bootstrap-s", "3", "--lag", "2"]) == 0
    err = capsys.readouterr().err
    timing = json.loads((out / "timing.json").read_text())
    span = timing["bootstrap_span_s"]
    assert abs(span - (session.t[timing["bootstrap_samples"] - 1] - session.t[0])) < 1e-9 and span > 6.0
    assert f"bootstrap calibration on the first {span:.1f} s (grown from 3 s: too little rotation" in err
    assert timing["bootstrap_note"].startswith(f"the first {span:.1f} s (grown from 3 s")
