"""Bad input never produces a traceback: each broken file gives a SessionError naming file and field.

The corpus is built in tmp_path at test time from a synthetic valid session; every case also checks
that the input file's bytes are unchanged.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from imugraph.errors import SessionError
from imugraph.io.readers import load_session
from imugraph.io.session import Session
from imugraph.io.validate import validate_session
from imugraph.io.writers import read_calibration_json

REPO = Path(__file__).resolve().parents[1]


def _npz(path: Path, s: Session, **override) -> Path:
    arrays = {"gyr": s.gyr, "acc": s.acc, "mag": s.mag, "t": s.t}
    arrays.update(override)
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


def _csv(path: Path, s: Session, drop: str = "") -> Path:
    names = ["t"] + [f"{q}_{a}" for q in ("gyr", "acc", "mag") for a in "xyz"]
    table = np.column_stack([s.t, s.gyr, s.acc, s.mag])
    keep = [i for i, nm in enumerate(names) if nm != drop]
    np.savetxt(path, table[:, keep], delimiter=",", header=",".join(names[i] for i in keep), comments="")
    return path


def _truncate(path: Path) -> Path:
    data = path.read_bytes()
    cut = len(data) // 2
    while data[cut - 1:cut] == b"\n":          # cut mid-line so a CSV ends with a partial row
        cut += 1
    path.write_bytes(data[:cut])
    return path


def _mat(path: Path, s: Session, drop: str = "") -> Path:
    import scipy.io

    fields = {"imu_gyr": s.gyr, "imu_acc": s.acc, "imu_mag": s.mag, "sampling_rate": np.array([[100.0]])}
    scipy.io.savemat(path, {k: v for k, v in fields.items() if k != drop})
    return path


def _cases(s: Session) -> dict[str, tuple[Callable[[Path], Path], str, str]]:
    """name → (builder(tmp_dir) → file, expected field, a word the message must contain)."""
    n = s.n
    gyr_run = s.gyr.copy()
    gyr_run[100:120] = np.nan
    t_gap = s.t.copy()
    t_gap[1000:] += 1.0
    t_unsorted = s.t.copy()
    t_unsorted[[500, 501]] = t_unsorted[[501, 500]]
    t_dup = s.t.copy()
    t_dup[700] = t_dup[699]
    gyr_sat = s.gyr.copy()
    gyr_sat[:, 1] = np.clip(gyr_sat[:, 1], -0.15, 0.15)
    acc_sat = s.acc.copy()
    acc_sat[300:310, 0] = 2 * 9.81 * 8.0
    t_nan = s.t.copy()
    t_nan[10] = np.nan
    fast = replace(s, gyr=s.gyr * 4.0)
    return {
        "nan_run": (lambda d: _npz(d / "nan_run.npz", s, gyr=gyr_run), "gyr", "100..119"),
        "gap": (lambda d: _npz(d / "gap.npz", s, t=t_gap), "t", "gap"),
        "unsorted": (lambda d: _npz(d / "unsorted.npz", s, t=t_unsorted), "t", "unsorted"),
        "duplicate": (lambda d: _npz(d / "dup.npz", s, t=t_dup), "t", "duplicate"),
        "nan_time": (lambda d: _npz(d / "nan_time.npz", s, t=t_nan), "t", "non-finite"),
        "gyr_2_columns": (lambda d: _npz(d / "gyr2.npz", s, gyr=s.gyr[:, :2]), "gyr", "shape"),
        "acc_extra_rows": (lambda d: _npz(d / "acc_rows.npz", s, acc=np.vstack([s.acc, s.acc[:5]])), "acc", "rows"),
        "mag_transposed": (lambda d: _npz(d / "mag_T.npz", s, mag=s.mag.T), "mag", "shape"),
        "gyr_deg_slow": (lambda d: _npz(d / "deg_slow.npz", s, gyr=np.rad2deg(s.gyr)), "gyr", "deg/s"),
        "gyr_deg_fast": (lambda d: _npz(d / "deg_fast.npz", fast, gyr=np.rad2deg(fast.gyr)), "gyr", "deg/s"),
        "acc_in_g": (lambda d: _npz(d / "acc_g.npz", s, acc=s.acc / 9.80665), "acc", "looks like g"),
        "gyr_saturated": (lambda d: _npz(d / "gyr_sat.npz", s, gyr=gyr_sat), "gyr", "axis y saturated"),
        "acc_saturated": (lambda d: _npz(d / "acc_sat.npz", s, acc=acc_sat), "acc", "axis x saturated"),
        "mag_all_nan": (lambda d: _npz(d / "mag_nan.npz", s, mag=np.full((n, 3), np.nan)), "mag", "all NaN"),
        "too_short": (lambda d: _npz(d / "short.npz", s.slice(0, 30)), "t", "too short"),
        "no_samples": (lambda d: _npz(d / "none.npz", s.slice(0, 0)), "t", "empty"),
        "missing_acc": (lambda d: _npz(d / "no_acc.npz", s, acc=None), "acc", "missing"),
        "missing_rate": (lambda d: _npz(d / "no_rate.npz", s, t=None), "rate", "neither"),
        "bad_rate": (lambda d: _npz(d / "bad_rate.npz", s, t=None, rate=np.array([-5.0])), "rate", "positive"),
        "text_as_npz": (lambda d: _write(d / "text.npz", b"t,gyr_x\n0,1\n"), "file", "text, not a zip"),
        "empty_npz": (lambda d: _write(d / "empty.npz", b""), "file", "empty"),
        "empty_csv": (lambda d: _write(d / "empty.csv", b""), "file", "empty"),
        "truncated_npz": (lambda d: _truncate(_npz(d / "trunc.npz", s)), "file", "npz"),
        "truncated_mat": (lambda d: _truncate(_mat(d / "trunc.mat", s)), "file", "MATLAB"),
        "truncated_csv": (lambda d: _truncate(_csv(d / "trunc.csv", s)), "", "truncated"),
        "mat_missing_field": (lambda d: _mat(d / "no_mag.mat", s, drop="imu_mag"), "imu_mag", "missing"),
        "mat_unknown": (lambda d: _mat(d / "alien.mat", s, drop="imu_gyr"), "imu_gyr", "neither"),
        "csv_missing_column": (lambda d: _csv(d / "no_gz.csv", s, drop="gyr_z"), "gyr_z", "missing"),
        "csv_text_cell": (lambda d: _text_cell(_csv(d / "text_cell.csv", s)), "acc_y", "oops"),
        "truncated_hdf5": (lambda d: _truncate(_hdf5(d / "trunc.hdf5", s)), "file", "HDF5"),
        "xsens_no_rate": (lambda d: _xsens_no_rate(d / "mtw.txt", s), "Update Rate", "Update Rate"),
    }


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _text_cell(path: Path) -> Path:
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")
    cells[5] = "oops"                      # column 5 = acc_y
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return path


def _hdf5(path: Path, s: Session) -> Path:
    import h5py

    with h5py.File(path, "w") as f:
        for k, v in (("imu_gyr", s.gyr), ("imu_acc", s.acc), ("imu_mag", s.mag)):
            f.create_dataset(k, data=v)
    return path


def _xsens_no_rate(path: Path, s: Session) -> Path:
    head = "// Start Time: Unknown\n// Filter Profile: human\n"
    cols = "PacketCounter,SampleTimeFine,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z,Mag_X,Mag_Y,Mag_Z\n"
    table = np.column_stack([np.arange(s.n), s.acc, s.gyr, s.mag])
    rows = "\n".join(f"{int(r[0])},," + ",".join(f"{v:.6f}" for v in r[1:]) for r in table)
    path.write_text(head + cols + rows + "\n")
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def corpus(tmp_path_factory, valid_session) -> dict[str, tuple[Path, str, str]]:
    d = tmp_path_factory.mktemp("corpus")
    return {name: (build(d), field, word) for name, (build, field, word) in _cases(valid_session).items()}


CASES = [
    "nan_run", "gap", "unsorted", "duplicate", "nan_time", "gyr_2_columns", "acc_extra_rows", "mag_transposed",
    "gyr_deg_slow", "gyr_deg_fast", "acc_in_g", "gyr_saturated", "acc_saturated", "mag_all_nan", "too_short",
    "no_samples", "missing_acc", "missing_rate", "bad_rate", "text_as_npz", "empty_npz", "empty_csv",
    "truncated_npz", "truncated_mat", "truncated_csv", "mat_missing_field", "mat_unknown", "csv_missing_column",
    "csv_text_cell", "truncated_hdf5", "xsens_no_rate"]


def test_case_list_covers_the_corpus(valid_session):
    assert sorted(CASES) == sorted(_cases(valid_session))


def test_the_clean_source_session_loads(tmp_path, valid_session):
    """Control: the unbroken session passes, so each failure below comes from its defect."""
    s = load_session(_npz(tmp_path / "ok.npz", valid_session))
    assert s.n == valid_session.n
    s = load_session(_csv(tmp_path / "ok.csv", valid_session))
    assert np.allclose(s.gyr, valid_session.gyr)


@pytest.mark.parametrize("name", CASES)
def test_bad_file_raises_session_error_naming_file_and_field(corpus, name):
    path, field, word = corpus[name]
    before = _sha(path)
    with pytest.raises(SessionError) as info:
        load_session(path)
    msg = str(info.value)
    assert path.name in msg
    if field:
        assert f"field '{field}'" in msg, msg
        assert info.value.field == field
    else:                                   # truncated CSV: the field is the first missing column
        assert info.value.field in {"t"} | {f"{q}_{a}" for q in ("gyr", "acc", "mag") for a in "xyz"}, msg
    assert word in msg, msg
    assert "\n" not in msg
    assert _sha(path) == before, "the input file was modified"


def test_isolated_nan_is_repaired_without_touching_the_input(valid_session):
    gyr = valid_session.gyr.copy()
    gyr[400, 1] = np.nan
    acc = valid_session.acc.copy()
    acc[900:902] = np.nan
    s = replace(valid_session, gyr=gyr, acc=acc)
    out = validate_session(s)
    assert out is not s
    assert out.meta["repaired"] == {"gyr": [400], "acc": [900, 901]}
    expected = 0.5 * (gyr[399, 1] + gyr[401, 1])          # midpoint of equally spaced neighbours
    assert out.gyr[400, 1] == pytest.approx(expected)
    assert np.isnan(s.gyr[400, 1]) and np.isnan(s.acc[900:902]).all()   # input unchanged
    assert "repaired" not in s.meta


def test_clean_session_is_returned_as_is(valid_session):
    assert validate_session(valid_session) is valid_session


def test_declared_gaps_are_accepted_but_others_are_not(valid_session):
    t = valid_session.t.copy()
    t[1000:] += 1.0
    gapped = replace(valid_session, t=t)
    with pytest.raises(SessionError, match="gap of 1.01 s"):
        validate_session(gapped)
    declared = replace(gapped, meta={"gaps": [[float(t[999]), float(t[1000])]]})
    assert validate_session(declared) is declared


def test_skip_lets_a_noise_free_constant_rate_pass(valid_session):
    gyr = np.tile([0.0, 0.0, 0.2], (valid_session.n, 1))
    s = replace(valid_session, gyr=gyr)
    with pytest.raises(SessionError, match="saturated"):
        validate_session(s)
    assert validate_session(s, skip=("saturation", "units")) is s


@pytest.mark.parametrize("content,field", [
    ("{not json", "file"),
    ('{"D": [[1, 0], [0, 1]], "o": [0, 0, 0], "dip_deg": 60}', "D"),
    ('{"D": [[1, 0, 0], [0, 1, 0], [0, 0, 0]], "o": [0, 0, 0], "dip_deg": 60}', "D"),
    ('{"D": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "dip_deg": 60}', "o"),
    ('{"D": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "o": [0, 0, "x"], "dip_deg": 60}', "o"),
    ("[1, 2, 3]", "file"),
])
def test_bad_calibration_json(tmp_path, content, field):
    path = tmp_path / "calibration.json"
    path.write_text(content)
    with pytest.raises(SessionError) as info:
        read_calibration_json(path)
    assert info.value.field == field
    assert "calibration.json" in str(info.value)


def test_missing_calibration_json(tmp_path):
    with pytest.raises(SessionError, match="no such file"):
        read_calibration_json(tmp_path / "nope.json")


def _run_cli(path: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "imugraph.cli", "calibrate", str(path), "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=300, cwd=REPO)


NO_CLI = importlib.util.find_spec("imugraph.cli") is None


@pytest.mark.skipif(NO_CLI, reason="imugraph.cli not written yet")
@pytest.mark.parametrize("name", ["nan_run", "text_as_npz", "truncated_csv", "acc_in_g"])
def test_cli_reports_one_line_and_no_traceback(corpus, tmp_path, name):
    """With --quiet (no progress lines) stderr is exactly the one error line."""
    path = corpus[name][0]
    before = _sha(path)
    proc = _run_cli(path, tmp_path / "out", "--quiet")
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("imugraph: error: ") and path.name in lines[0]
    assert "Traceback" not in proc.stderr
    assert _sha(path) == before
    assert not (tmp_path / "out" / "calibration.json").exists()


@pytest.mark.skipif(NO_CLI, reason="imugraph.cli not written yet")
def test_cli_without_quiet_has_one_error_line(corpus, tmp_path):
    """Without --quiet progress lines may precede it, but there is exactly one error line."""
    path = corpus["gap"][0]
    proc = _run_cli(path, tmp_path / "out")
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if path.name in ln and "error" in ln]
    assert len(errors) == 1 and "field 't'" in errors[0], proc.stderr
