"""Session 21, helper F21b: the output-side defects of the acceptance run (docs/formats.md "Session 21: output
fixes"). Each test fails on the code before the fix. Inputs are simulated (imugraph.sim) or built in tmp_path."""

from __future__ import annotations

import argparse
import json
import re
from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.cli import build_parser, main
from imugraph.commands import common
from imugraph.errors import SessionError
from imugraph.geometry import quat_mul, rotvec_to_quat
from imugraph.sim.scenario import distorted_session


@pytest.fixture(scope="module")
def sim():
    return distorted_session(3, duration_s=20.0, rate_hz=50.0)


# ---------------------------------------------------------------- (2) dead magnetometer in the scores
def test_scores_of_a_dead_magnetometer_are_na_not_an_error(sim):
    from imugraph.commands.report import score_lines

    session, truth = sim
    dead = session.with_mag(np.zeros_like(session.mag))
    scores = common.score(dead, truth.to_calibration(), session.quat)     # raised EvaluationError before
    assert np.isnan(scores.norm_before)
    line = score_lines(scores)[0]
    assert "n/a" in line and "nan" not in line


# ---------------------------------------------------------------- (5) heading.png aligned as the console score
def test_heading_figure_removes_the_nav_frame_offset_as_the_score_does(tmp_path, sim):
    from imugraph.io.figures import plot_heading

    session, _ = sim
    rz = rotvec_to_quat(np.array([0.0, 0.0, np.deg2rad(90.0)]))
    q_est = quat_mul(np.broadcast_to(rz, session.quat.shape), session.quat)   # same motion, nav frame 90° off
    fig = plot_heading(tmp_path / "h.png", session.t, q_est, session.quat, align=True,
                       reference_label="truth")
    labels = [t.get_text() for t in fig.axes[1].get_legend().get_texts()]
    rms = [float(re.search(r"RMS ([0-9.]+)°", x).group(1)) for x in labels]
    assert max(rms) < 0.05, labels                      # unaligned: 90°
    assert "heading offset -90.00°" in fig.axes[1].get_title()     # Rz(ψ)·estimate = reference


# ---------------------------------------------------------------- (6) calibration.png: the model's field
def test_calibration_figure_uses_the_disturbance_corrected_field(tmp_path, sim, monkeypatch):
    import imugraph.io.figures as figures

    session, truth = sim
    cal = truth.to_calibration()
    cal.disturbances = [{"t_start": 5.0, "t_end": 8.0, "offset": [30.0, 0.0, 0.0], "modelled": True}]
    mag = session.mag.copy()
    mag[(session.t >= 5.0) & (session.t <= 8.0)] += [30.0, 0.0, 0.0]       # a magnet the model explains
    session = session.with_mag(mag)
    seen = {}
    monkeypatch.setattr(figures, "plot_calibration", lambda path, raw, cal_, t, res, **kw: seen.update(cal=cal_, **kw))
    monkeypatch.setattr(figures, "plot_heading", lambda *a, **kw: seen.update(heading=kw))
    est = SimpleNamespace(calibration=cal, t=session.t, quat=session.quat, residuals={},
                          info={"velocity": np.zeros((3, 3))})
    common.write_estimate(tmp_path, session, est, common.Progress(quiet=True))
    norm = np.linalg.norm(seen["cal"], axis=1)
    assert np.nanmax(np.abs(norm - 1.0)) < 0.2                 # cal.apply(raw) reaches |m| ≈ 1.5 in the window
    assert seen["not_in_cost"] == ("acc",)                     # velocity model: acc residual said not in cost
    assert seen["heading"]["align"] is True


# ---------------------------------------------------------------- (7) diagnosis.md table cells
def test_diagnosis_markdown_rows_have_as_many_cells_as_the_header():
    from imugraph.diagnose.gap import CHANNELS
    from imugraph.diagnose.report import markdown

    s = SimpleNamespace(name="x", n=10, t=np.arange(10.0), rate=1.0, source="x.npz")
    per = {c: 1.0 for c in CHANNELS}
    eff = SimpleNamespace(name="magnetic_disturbance", channel="mag", t_start=1.0, t_end=2.0, error=None,
                          gap_before=1.0, gap_after=0.5, shrink=0.5, penalised=0.4, loglik_gain=0.1, n_params=4,
                          size={"value": 1.32, "threshold": 0.1, "unit": "fraction of |m|"}, significant=True,
                          relevant=True, stage="refit")
    bad = SimpleNamespace(name="saturation", channel="acc", error="a | b", t_start=None, t_end=None)
    diag = SimpleNamespace(real=SimpleNamespace(session=s, info={}), verdict="magnetic_disturbance", gap=per,
                           gap_raw=per, null_gap=per, locations=[], effects=[eff, bad])
    lines = markdown(diag, {"gap": "g.png", "residuals": "r.png"}).splitlines()
    head = next(i for i, x in enumerate(lines) if x.startswith("| rank |"))
    cells = lambda row: len(re.split(r"(?<!\\)\|", row)) - 2       # noqa: E731 — unescaped pipes
    assert cells(lines[head + 2]) == cells(lines[head]) == 14
    assert cells(lines[head + 3]) == 14


# ---------------------------------------------------------------- (8) a device's own orientation is no truth
def test_onboard_orientation_is_called_reference_not_truth(sim):
    from imugraph.commands.report import score_lines

    session, truth = sim
    ahrs = session.__class__(**{**session.__dict__, "meta": {"quat_source": "x-IMU3 onboard AHRS (estimate)"}})
    text = "\n".join(score_lines(common.score(ahrs, truth.to_calibration(), session.quat)))
    assert "vs reference [x-IMU3 onboard AHRS (estimate)]" in text and "vs truth" not in text
    assert "vs truth" in "\n".join(score_lines(common.score(session, truth.to_calibration(), session.quat)))


# ---------------------------------------------------------------- (10) batch: Ctrl-C and a cluster that fails
def test_batch_ctrl_c_writes_the_finished_sessions_summary(tmp_path, monkeypatch, capsys):
    import imugraph.batch as batch

    done = {"session": "a", "path": "a.npz", "out": str(tmp_path / "a"), "status": "ok", "time_s": 1.0,
            "error_deg": 0.5, "error": ""}

    def interrupted(*a, **kw):
        raise batch.BatchInterrupted([done], 2)

    monkeypatch.setattr(batch, "run_batch", interrupted)
    rc = main(["batch", "a.npz", "b.npz", "--out", str(tmp_path), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 130 and len(err) == 1 and err[0].startswith("imugraph: interrupted")
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc["interrupted"] is True and [r["session"] for r in doc["sessions"]] == ["a"]


def test_batch_collect_cancels_unfinished_futures_on_ctrl_c():
    from tqdm import tqdm

    import imugraph.batch as batch

    class Fut:
        def __init__(self, key, finished):
            self.key, self.status = key, "finished" if finished else "pending"

        def done(self):
            return self.status == "finished"

        def result(self, timeout=None):
            return {"session": self.key, "status": "ok"}

    futs = iter([Fut("k0", True), Fut("k1", False)])
    client = SimpleNamespace(submit=lambda *a, **kw: next(futs), cancelled=[])
    client.cancel = lambda fs: client.cancelled.extend(f.key for f in fs)

    def as_completed(fs):
        raise KeyboardInterrupt
        yield                                                   # pragma: no cover

    rows = [None, None]
    with pytest.raises(KeyboardInterrupt):
        batch._collect(client, ["a.npz", "b.npz"], ["A", "B"], None, rows, False, as_completed, tqdm)
    assert client.cancelled == ["k1"] and rows[0]["session"] == "k0" and rows[1] is None


def test_local_cluster_that_fails_to_start_is_one_error(monkeypatch):
    import distributed

    import imugraph.batch as batch

    def broken(*a, **kw):
        raise RuntimeError("Nanny failed to start.")

    monkeypatch.setattr(distributed, "LocalCluster", broken)
    with pytest.raises(SessionError, match="field 'workers'.*Nanny failed to start"):
        with batch.dask_client(None, 1):
            pass


# ---------------------------------------------------------------- (15) flags that would be ignored
def test_stream_flags_this_combination_ignores_are_named():
    from imugraph.commands.stream import ignored_flags

    p = build_parser()
    assert ignored_flags(p.parse_args(["stream", "x.npz", "--lag", "2", "--calib-json-end-graph"]))
    assert ignored_flags(p.parse_args(["stream", "x.npz", "--disturb-offsets", "--no-calib-states"]))
    assert not ignored_flags(p.parse_args(["stream", "x.npz", "--lag", "2"]))
    assert not ignored_flags(p.parse_args(["stream", "x.npz", "--calib-json-end-graph"]))


def test_mocap_hinges_without_such_joints_are_reported():
    from imugraph.body.skeleton import lower_body
    from imugraph.commands.mocap import hinge_segments

    ignored: list = []
    skel = lower_body()
    assert hinge_segments("knees,elbows", skel, ignored) == ("RightLowerLeg", "LeftLowerLeg")
    assert ignored and all(x.startswith("elbows") for x in ignored)


def test_bench_trials_not_in_the_data_folder_are_refused(tmp_path):
    from imugraph.commands.bench import check_trials

    (tmp_path / "broad").mkdir()
    (tmp_path / "broad" / "01_undisturbed.mat").write_bytes(b"")
    args = argparse.Namespace(trials="01,99", data_dir=str(tmp_path))
    with pytest.raises(SessionError, match="field 'trials'.*99"):
        check_trials(args)
    assert check_trials(argparse.Namespace(trials="01", data_dir=str(tmp_path))) == ["01"]


# ---------------------------------------------------------------- (16) smaller output defects
def test_mocap_timing_reports_the_real_time_factor_with_the_bootstrap():
    from imugraph.commands.mocap import timing_summary

    info = {"update_s": [0.1] * 10, "realtime_factor": 20.0, "bootstrap": {"seconds": 8.0}}
    t = timing_summary(info, 20.0)
    assert t["realtime_factor"] == 20.0
    assert t["realtime_factor_with_bootstrap"] == pytest.approx(20.0 / 9.0)


def test_stream_arrival_counts_are_a_readable_line():
    from imugraph.commands.stream import arrival_line

    line = arrival_line({"accepted": 10, "duplicates": 3, "gaps": 2, "mag_samples": 5, "invalid": 0})
    assert line == "  arrival: 3 duplicate, 2 gaps"
    assert arrival_line({"accepted": 4}) == ""


def test_an_unwritable_out_fails_before_the_computation(monkeypatch, capsys, tmp_path):
    import imugraph.commands.calibrate as calibrate

    target = "/proc/self/imugraph_out_test"      # /proc/self exists and takes no new file, even for root
    try:
        open(target, "w").close()
        pytest.skip("/proc/self is writable here")
    except OSError:
        pass
    session_file = tmp_path / "s.npz"
    assert main(["simulate", "--out", str(session_file), "--duration", "20", "--quiet"]) == 0
    monkeypatch.setattr(calibrate, "estimate_calibration", lambda *a, **kw: pytest.fail("computed first"))
    assert main(["calibrate", str(session_file), "--out", "/proc/self", "--quiet"]) == 2
    assert "field 'out'" in capsys.readouterr().err


def test_a_failed_run_leaves_no_empty_out_folder(monkeypatch, tmp_path):
    import imugraph.commands.calibrate as calibrate
    from imugraph.errors import CalibrationError

    session_file = tmp_path / "s.npz"
    assert main(["simulate", "--out", str(session_file), "--duration", "20", "--quiet"]) == 0

    def refuse(*a, **kw):
        raise CalibrationError("too little rotation")

    monkeypatch.setattr(calibrate, "estimate_calibration", refuse)
    out = tmp_path / "new" / "deeper"
    assert main(["calibrate", str(session_file), "--out", str(out), "--quiet"]) == 2
    assert not (tmp_path / "new").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    assert main(["calibrate", str(session_file), "--out", str(kept), "--quiet"]) == 2
    assert kept.is_dir()                                         # a folder the user made stays


# ---------------------------------------------------------------- (13) simulate: CSV and effects
def test_simulate_csv_holds_the_documented_columns_exactly(tmp_path):
    from imugraph.io.readers import load_session

    assert main(["simulate", "--out", str(tmp_path / "s.csv"), "--duration", "20", "--quiet"]) == 0
    assert main(["simulate", "--out", str(tmp_path / "s.npz"), "--duration", "20", "--quiet"]) == 0
    head = (tmp_path / "s.csv").read_text().splitlines()[0]
    assert head == "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z"
    a, b = load_session(tmp_path / "s.csv"), np.load(tmp_path / "s.npz")
    for key in ("t", "gyr", "acc", "mag"):
        np.testing.assert_array_equal(getattr(a, key), b[key])


def test_simulate_refuses_another_session_format_and_unknown_effects(tmp_path):
    assert main(["simulate", "--out", str(tmp_path / "s.mat"), "--duration", "20", "--quiet"]) == 2
    assert main(["simulate", "--out", str(tmp_path / "s.npz"), "--effect", "nope", "--quiet"]) == 2
    assert list(tmp_path.iterdir()) == []


def test_simulate_effect_is_injected_and_recorded(tmp_path):
    plain, hit = tmp_path / "plain.npz", tmp_path / "hit.npz"
    assert main(["simulate", "--out", str(plain), "--duration", "20", "--quiet"]) == 0
    assert main(["simulate", "--out", str(hit), "--duration", "20", "--effect", "gyro_bias_drift", "--quiet"]) == 0
    a, b = np.load(plain), np.load(hit)
    effects = json.loads(str(b["effects"]))
    assert list(effects) == ["gyro_bias_drift"] and effects["gyro_bias_drift"]["params"]["drift_deg_s"] > 0
    assert not np.allclose(a["gyr"], b["gyr"])
    np.testing.assert_array_equal(a["mag"], b["mag"])           # the gyro effect leaves the other channels

