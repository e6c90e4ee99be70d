"""Session 21 input checks (acceptance-run defects 1–4, 9, 11–14, 16): bad input gives one line naming the field.

Every bad input is built in tmp_path from a simulated session (imugraph.sim) or by damaging a written copy; the
expected messages are the contract of docs/formats.md ("Session 21: input checks added"), not computed by the code
under test.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imugraph.calibration.result import Calibration
from imugraph.cli import main
from imugraph.errors import CalibrationError, SessionError
from imugraph.io.readers import load_session
from imugraph.io.writers import read_calibration_json, write_calibration_json
from imugraph.sim.scenario import distorted_session

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sim():
    """(session, truth): 30 s at 100 Hz, rotation about all axes, distorted magnetometer."""
    return distorted_session(3, 30.0, 100.0)


def _npz(path: Path, session, **override) -> Path:
    arrays = {"t": session.t, "gyr": session.gyr, "acc": session.acc, "mag": session.mag}
    arrays.update(override)
    np.savez(path, **arrays)
    return path


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("imugraph: error: ") and "Traceback" not in "\n".join(err)
    return err[-1]


# (1) a time base in ms (or any implausible rate) --------------------------------------------------------------

def test_time_stamps_in_ms_are_refused_naming_t(sim, tmp_path, capsys):
    session, _ = sim
    path = _npz(tmp_path / "t_ms.npz", session, t=session.t * 1000.0)
    with pytest.raises(SessionError) as exc:
        load_session(path)
    assert exc.value.field == "t" and "divide by 1000" in exc.value.expected
    assert "median step 10 s" in exc.value.found                   # 100 Hz stamps in ms: 10 "s" per step
    out = tmp_path / "out"
    assert main(["calibrate", str(path), "--out", str(out), "--quiet"]) == 2
    assert "field 't'" in _one_error_line(capsys) and not out.exists()


def test_time_base_too_fast_or_too_long_is_refused(sim, tmp_path):
    from imugraph.io.session import Session
    from imugraph.io.validate import validate_session

    session, _ = sim
    with pytest.raises(SessionError, match="field 't'.*divide by 1000"):
        load_session(_npz(tmp_path / "fast.npz", session, t=session.t / 1000.0))         # 100 kHz
    with pytest.raises(SessionError, match="field 't'.*divide by 1000"):                 # a 1 kHz log in ms: "1 Hz"
        load_session(_npz(tmp_path / "khz.npz", session, t=np.arange(session.n) * 1.0))
    n = 90_000                                                                          # 1 Hz over 25 h
    long = Session(t=np.arange(n, dtype=float), gyr=np.zeros((n, 3)), acc=np.tile([0, 0, 9.81], (n, 1)),
                   mag=np.ones((n, 3)))
    with pytest.raises(SessionError, match="field 't'.*over 89999 s"):
        validate_session(long)


def test_valid_time_bases_still_load(sim, tmp_path):
    session, _ = sim
    assert load_session(_npz(tmp_path / "ok.npz", session)).n == session.n
    unix = load_session(_npz(tmp_path / "unix.npz", session, t=session.t + 1.7e9))        # epoch seconds
    assert unix.n == session.n


# (2) a dead magnetometer ------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind, words", [("zero", "all zero"), ("const", "constant on every axis"),
                                         ("axis", "constant on axis y")])
def test_dead_magnetometer_is_refused_at_load(sim, tmp_path, kind, words):
    session, _ = sim
    mag = np.array(session.mag, float)
    if kind == "zero":
        mag[:] = 0.0
    elif kind == "const":
        mag[:] = [10.0, 20.0, 30.0]
    else:
        mag[:, 1] = 7.0
    with pytest.raises(SessionError) as exc:
        load_session(_npz(tmp_path / f"mag_{kind}.npz", session, mag=mag))
    assert exc.value.field == "mag" and words in exc.value.found


@pytest.mark.parametrize("command", [["stream", "--lag", "2"], ["stream"], ["diagnose"], ["calibrate"]])
def test_dead_magnetometer_commands_exit_2_without_traceback(sim, tmp_path, capsys, command):
    session, _ = sim
    path = _npz(tmp_path / "mag_zero.npz", session, mag=np.zeros_like(session.mag))
    out = tmp_path / "out"
    rc = main([command[0], str(path), "--out", str(out), "--quiet", *command[1:]])
    line = _one_error_line(capsys)
    assert rc == 2 and "field 'mag'" in line and "dead or disconnected magnetometer" in line


# (3) malformed disturbance windows in calibration.json ------------------------------------------------------

def _cal_json(tmp_path: Path, windows) -> Path:
    path = tmp_path / "calibration.json"
    write_calibration_json(path, Calibration(D=np.eye(3), o=np.zeros(3), dip_deg=60.0))
    d = json.loads(path.read_text())
    d["disturbances"] = windows
    path.write_text(json.dumps(d))
    return path


@pytest.mark.parametrize("window, field", [
    ({"t_start": 1.0}, "disturbances[0].t_end"),
    ({"t_start": 1.0, "t_end": 5.0, "offset": [1.0, 2.0], "modelled": True}, "disturbances[0].offset"),
    ({"t_start": "a", "t_end": 5.0, "offset": [1, 2, 3], "modelled": True}, "disturbances[0].t_start"),
    ({"t_start": 6.0, "t_end": 5.0}, "disturbances[0].t_end"),
    ({"t_start": 1.0, "t_end": 5.0, "offset": [1, 2, 3], "modelled": "yes"}, "disturbances[0].modelled"),
])
def test_malformed_disturbance_window_names_the_field(tmp_path, window, field):
    with pytest.raises(SessionError) as exc:
        read_calibration_json(_cal_json(tmp_path, [window]))
    assert exc.value.field == field


def test_well_formed_disturbance_windows_still_apply(tmp_path):
    path = _cal_json(tmp_path, [{"t_start": 1, "t_end": 2, "offset": [1, 0, 0], "modelled": True},
                                {"t_start": 3.0, "t_end": 4.0, "offset": None, "modelled": False}])
    cal = read_calibration_json(path)
    t = np.arange(0.0, 5.0, 0.5)
    y = cal.corrected(t, np.ones((t.size, 3)))
    assert np.allclose(y[(t >= 1) & (t <= 2), 0], 0.0) and np.isnan(y[(t >= 3) & (t <= 4)]).all()
    assert np.allclose(y[t < 1], 1.0)


def test_smooth_with_malformed_windows_exits_2(sim, tmp_path, capsys):
    session, _ = sim
    path = _npz(tmp_path / "s.npz", session)
    cal = _cal_json(tmp_path, [{"t_start": 1.0}])
    assert main(["smooth", str(path), "--calibration", str(cal), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "disturbances[0].t_end" in _one_error_line(capsys)


# (4) a calibration of another sensor -----------------------------------------------------------------------

def test_calibration_of_another_sensor_is_refused(sim):
    from imugraph.io.validate import check_calibration_applies

    session, truth = sim
    own = Calibration(D=truth.D, o=truth.o, dip_deg=float(np.degrees(truth.dip_rad)))
    assert 0.9 < check_calibration_applies(session, own) < 1.1
    other = Calibration(D=truth.D / 5.0, o=truth.o, dip_deg=60.0)        # |m| ≈ 5, as BROAD's D on an MPU9150
    with pytest.raises(SessionError) as exc:
        check_calibration_applies(session, other, "broad.json")
    assert exc.value.field == "calibration" and "another sensor" in exc.value.found and "broad.json" in exc.value.found


# (9) the little-rotation refusal names --allow-weak once ---------------------------------------------------

def test_too_little_rotation_names_allow_weak_once():
    from imugraph.calibration.coverage import check_coverage

    session, _ = distorted_session(0, 10.0, 100.0)      # 10 s: too little rotation (f21a_demo_min_duration)
    with pytest.raises(CalibrationError) as exc:
        check_coverage(session)
    text = str(exc.value)
    assert text.count("--allow-weak") == 1 and text.count("rotate the sensor about all three axes") == 1


# (11) tab- and semicolon-separated Xsens MTw exports -------------------------------------------------------

_MTW_COLS = ["PacketCounter", "SampleTimeFine", "Acc_X", "Acc_Y", "Acc_Z", "Gyr_X", "Gyr_Y", "Gyr_Z",
             "Mag_X", "Mag_Y", "Mag_Z"]


def _mtw(path: Path, session, sep: str = ",", decimal: str = ".", nan_rows: slice | None = None) -> Path:
    """An MT Manager export of `session` at 100 Hz, time from PacketCounter (SampleTimeFine left empty)."""
    acc = np.array(session.acc, float)
    if nan_rows is not None:
        acc[nan_rows] = np.nan
    lines = ["// Start Time: Unknown", "// Update Rate: 100.0Hz", "// Filter Profile: human (46.1)",
             sep.join(_MTW_COLS)]
    for k in range(session.n):
        vals = [f"{v:.6f}" for v in (*acc[k], *session.gyr[k], *session.mag[k])]
        vals = ["" if "nan" in v else v.replace(".", decimal) for v in vals]
        lines.append(sep.join([str(1000 + k), ""] + vals))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("sep, decimal", [("\t", "."), (";", "."), (";", ","), ("\t", ",")])
def test_tab_and_semicolon_mtw_exports_read_as_the_comma_one(sim, tmp_path, sep, decimal):
    session, _ = sim
    ref = load_session(_mtw(tmp_path / "comma.txt", session))
    other = load_session(_mtw(tmp_path / "other.txt", session, sep, decimal))
    for name in ("t", "gyr", "acc", "mag"):
        np.testing.assert_array_equal(getattr(other, name), getattr(ref, name))


# (12) a NaN run in a gaittoolbox sensor file: index and time in the message --------------------------------

def test_gaittoolbox_nan_message_gives_samples_time_and_file(sim, tmp_path):
    from imugraph.io.gaittoolbox import SENSOR_IDS, read_gaittoolbox

    session, _ = sim
    for seg, sid in SENSOR_IDS.items():
        _mtw(tmp_path / f"S99-Trial-Walk-1-000_{sid}.txt", session,
             nan_rows=slice(300, 321) if seg == "Pelvis" else None)
    with pytest.raises(SessionError) as exc:
        read_gaittoolbox(tmp_path)
    e = exc.value
    assert e.field == "sensors[Pelvis].acc" and e.source.endswith("00B40B91.txt")
    assert "samples 300..320" in e.found and "t = 3.00..3.20 s" in e.found and "21 samples" in e.found


# (13) Rasteiro's XSENS.mat: the commercial AHRS is named as refused ----------------------------------------

def test_rasteiro_xsens_mat_is_refused_as_commercial_ahrs(tmp_path):
    import scipy.io

    folder = tmp_path / "DataSets" / "V_300" / "Sequencia1"
    folder.mkdir(parents=True)
    n = 200
    scipy.io.savemat(folder / "XSENS.mat", {"MATLABtime": np.arange(n)[None] / 100.0,
                                            "ABBquaternion": np.tile([[1.0], [0], [0], [0]], n),
                                            "SENSquat": np.tile([1.0, 0, 0, 0], (n, 1))})
    with pytest.raises(SessionError) as exc:
        load_session(folder / "XSENS.mat")
    assert "commercial AHRS" in exc.value.found and "refused" in exc.value.found


# (14) demo and simulate durations ---------------------------------------------------------------------------

def test_demo_too_short_names_the_minimum_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--duration", "10", "--out", str(out), "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert "field 'duration'" in line and "at least 20 s" in line and not out.exists()


def test_simulated_motion_shorter_than_its_rests_names_duration():
    from imugraph.sim.motion import random_rotation_motion

    with pytest.raises(SessionError) as exc:
        random_rotation_motion(5.0, 100.0, np.random.default_rng(0), rest_s=2.0, pauses=2)
    assert exc.value.field == "duration" and "7 s" in exc.value.expected
    assert "imugraph.sim" not in str(exc.value) and "rest_s/pauses" not in str(exc.value)


# (16) data-directory lookup and a closed stdout pipe --------------------------------------------------------

def test_find_session_searches_subfolders_and_says_where_it_looked(tmp_path, monkeypatch):
    from imugraph.config import find_session

    (tmp_path / "data" / "a" / "b").mkdir(parents=True)
    (tmp_path / "data" / "a" / "b" / "one.npz").write_bytes(b"x")
    for sub in ("a", "c"):
        (tmp_path / "data" / sub).mkdir(exist_ok=True)
        (tmp_path / "data" / sub / "two.npz").write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    data = str(tmp_path / "data")
    assert find_session("one.npz", data) == tmp_path / "data" / "a" / "b" / "one.npz"
    assert find_session("c/two.npz", data) == tmp_path / "data" / "c" / "two.npz"
    with pytest.raises(SessionError, match="2 matches"):
        find_session("two.npz", data)
    with pytest.raises(SessionError) as exc:
        find_session("none.npz", data)
    assert data in exc.value.found and str(tmp_path) in exc.value.found


def test_closed_stdout_pipe_exits_quietly(tmp_path):
    r, w = os.pipe()
    os.close(r)                                    # the reader (e.g. `| head`) has gone: writes get EPIPE
    code = "import sys; from imugraph.cli import main; sys.exit(main(sys.argv[1:]))"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    try:
        p = subprocess.run([sys.executable, "-c", code, "demo", "--duration", "20", "--quiet", "--out",
                            str(tmp_path / "d")], stdout=w, stderr=subprocess.PIPE, cwd=REPO, env=env, timeout=300)
    finally:
        os.close(w)
    assert p.returncode == 141 and p.stderr.decode().strip() == ""
