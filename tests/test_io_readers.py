"""Readers on every real format in the shared data (skipped when absent) and on synthetic files."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from imugraph.calibration.result import Calibration
from imugraph.geometry import quat_conj, quat_mul, quat_slerp, quat_to_rotvec, rotvec_to_quat
from imugraph.io.readers import load_session
from imugraph.io.writers import (atomic_write_bytes, atomic_write_text, read_calibration_json,
                                 write_calibration_json, write_orientation_npz)

G = 9.80665
BROAD02 = "broad/02_undisturbed_slow_rotation_B"
XSENS = "gaittoolbox/rawimu/S02-Trial-Walk-1-000_00B40B91.txt"
FUSION = "fusion/sensor_data.csv"
PELVIS = "xio_lower_body/pelvis 64F0EDBF (UDP)"
RASTEIRO = "rasteiro/DataSets/{}/Sequencia1/{}.mat"


def _rest_acc_norm(s) -> float:
    """Median |acc| over the samples where the gyro says the sensor is still (< 0.05 rad/s)."""
    still = np.linalg.norm(s.gyr, axis=1) < 0.05
    assert still.sum() > 50
    return float(np.median(np.linalg.norm(s.acc[still], axis=1)))


# ---------------------------------------------------------------- BROAD

def test_broad_mat_and_hdf5_agree(data_file):
    mat = load_session(data_file(BROAD02 + ".mat"))
    h5 = load_session(data_file(BROAD02 + ".hdf5"))
    assert mat.n == h5.n == 53240
    assert mat.rate == pytest.approx(2000.0 / 7.0, rel=1e-9)
    assert h5.meta["rate_source"] == "attribute"
    for name in ("t", "gyr", "acc", "mag", "quat"):
        np.testing.assert_array_equal(getattr(mat, name), getattr(h5, name), err_msg=name)
    np.testing.assert_array_equal(mat.movement, h5.movement)
    assert mat.movement.dtype == bool and 0 < mat.movement.sum() < mat.n


def test_broad_units(data_file):
    s = load_session(data_file(BROAD02 + ".mat"))
    assert _rest_acc_norm(s) == pytest.approx(9.81, abs=0.15)
    assert np.median(np.linalg.norm(s.mag, axis=1)) == pytest.approx(44.0, abs=3.0)   # µT
    assert np.abs(s.gyr).max() < 10.0                                                  # rad/s
    finite = np.all(np.isfinite(s.quat), axis=1)
    assert np.allclose(np.linalg.norm(s.quat[finite], axis=1), 1.0, atol=1e-6)
    assert s.meta["converted"] == []


def test_broad_hdf5_without_rate_uses_the_documented_default(tmp_path, valid_session):
    import h5py

    path = tmp_path / "trial.hdf5"
    with h5py.File(path, "w") as f:
        for k, v in (("imu_gyr", valid_session.gyr), ("imu_acc", valid_session.acc), ("imu_mag", valid_session.mag)):
            f.create_dataset(k, data=v.T)          # MATLAB-style (3, N) is accepted too
    s = load_session(path)
    assert s.meta["rate_source"] == "default"
    assert s.rate == pytest.approx(285.714, abs=1e-3)
    np.testing.assert_array_equal(s.gyr, valid_session.gyr)


# ---------------------------------------------------------------- Xsens MTw

def test_xsens_mtw(data_file):
    path = data_file(XSENS)
    s = load_session(path)
    assert s.n == 2503 and s.rate == pytest.approx(100.0)
    assert s.t[0] == 0.0 and s.t[-1] == pytest.approx(25.02)
    with open(path) as fh:                                  # first data row, read independently
        rows = [ln for ln in fh if not ln.startswith("//")]
    header, first = rows[0].strip().split(","), rows[1].strip().split(",")
    assert s.acc[0, 0] == float(first[header.index("Acc_X")])
    assert s.gyr[0, 2] == float(first[header.index("Gyr_Z")])
    assert s.quat[0, 0] == float(first[header.index("Quat_q0")])
    assert np.median(np.linalg.norm(s.acc, axis=1)) == pytest.approx(9.81, abs=0.3)
    assert np.median(np.linalg.norm(s.mag, axis=1)) == pytest.approx(1.0, abs=0.2)     # normalised a.u.
    assert np.allclose(np.linalg.norm(s.quat, axis=1), 1.0, atol=1e-3)
    assert "onboard" in s.meta["quat_source"] and s.meta["missing_packets"] == 0


def test_xsens_counter_wrap_and_missing_packet(tmp_path, valid_session):
    n = valid_session.n
    counter = (65000 + np.arange(n + 1)) % 65536                 # wraps after 536 samples
    counter = np.delete(counter, 1500)                           # one packet lost
    table = np.column_stack([valid_session.acc, valid_session.gyr, valid_session.mag])
    lines = ["// Update Rate: 100.0Hz",
             "PacketCounter,SampleTimeFine,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z,Mag_X,Mag_Y,Mag_Z"]
    lines += [f"{c},," + ",".join(f"{v:.9f}" for v in row) for c, row in zip(counter, table)]
    path = tmp_path / "mtw.txt"
    path.write_text("\n".join(lines) + "\n")
    s = load_session(path)
    expected_t = np.r_[np.arange(1500), np.arange(1501, n + 1)] / 100.0
    np.testing.assert_allclose(s.t, expected_t, atol=1e-12)
    assert s.meta["missing_packets"] == 1 and len(s.meta["gaps"]) == 1
    np.testing.assert_allclose(s.gyr, valid_session.gyr, atol=1e-9)


# ---------------------------------------------------------------- x-io

def test_fusion_csv_is_converted_and_held_mag_reduced(data_file):
    path = data_file(FUSION)
    s = load_session(path)
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        next(reader)
        raw = np.array([[float(v) for v in row] for row in reader])
    assert s.n == raw.shape[0]
    np.testing.assert_allclose(s.gyr, np.deg2rad(raw[:, 1:4]), rtol=1e-12)
    np.testing.assert_allclose(s.acc, raw[:, 4:7] * G, rtol=1e-12)
    assert "gyr: deg/s->rad/s" in s.meta["converted"] and "acc: g->m/s^2" in s.meta["converted"]
    assert _rest_acc_norm(s) == pytest.approx(9.81, abs=0.2)
    valid = s.mag_valid
    assert 18.0 < valid.sum() / (s.t[-1] - s.t[0]) < 21.0        # ~20 Hz updates in a ~99 Hz stream
    kept = s.mag[valid]
    assert not np.any(np.all(kept[1:] == kept[:-1], axis=1))     # no held copy survives
    changed = np.r_[True, np.any(raw[1:, 7:10] != raw[:-1, 7:10], axis=1)]
    np.testing.assert_array_equal(valid, changed)                # first row of each run kept
    np.testing.assert_array_equal(s.mag[valid], raw[changed, 7:10])


def test_ximu3_folder(data_file):
    path = data_file(PELVIS)
    s = load_session(path)
    inertial = np.loadtxt(path / "Inertial.csv", delimiter=",", skiprows=1)
    mag_raw = np.loadtxt(path / "Magnetometer.csv", delimiter=",", skiprows=1)
    assert s.n == inertial.shape[0]
    np.testing.assert_allclose(s.t, (inertial[:, 0] - inertial[0, 0]) * 1e-6)
    np.testing.assert_allclose(s.gyr, np.deg2rad(inertial[:, 1:4]))
    assert s.rate == pytest.approx(50.0, rel=0.01)
    assert np.median(np.linalg.norm(s.acc, axis=1)) == pytest.approx(9.81, abs=0.3)
    dt = np.diff(inertial[:, 0])
    assert s.meta["dropouts"]["count"] == int(np.sum(dt > 1.5 * np.median(dt))) > 0
    valid = s.mag_valid
    assert 0.9 * mag_raw.shape[0] < valid.sum() <= mag_raw.shape[0]
    # every placed sample is a row of Magnetometer.csv, on an inertial sample within half a step
    for i in np.flatnonzero(valid)[:: 25]:
        j = int(np.argmin(np.abs(mag_raw[:, 0] - inertial[i, 0])))
        assert abs(mag_raw[j, 0] - inertial[i, 0]) <= 0.5 * np.median(dt)
        np.testing.assert_array_equal(s.mag[i], mag_raw[j, 1:4])


# ---------------------------------------------------------------- Rasteiro

def _relative_rotation_error(s, window_s: float = 0.5) -> float:
    """Median |Log(truth_rel⁻¹ · gyro_rel)| / |truth_rel| over windows, best truth delay in [0, 0.3] s."""
    t, gyr = s.t, s.gyr - np.median(s.gyr[:50], axis=0)
    dq = rotvec_to_quat(gyr[:-1] * np.diff(t)[:, None])
    idx = np.searchsorted(t, np.arange(t[0] + 0.5, t[-1] - 0.5, window_s))
    rel_g = []
    for a, b in zip(idx[:-1], idx[1:]):
        q = np.array([1.0, 0.0, 0.0, 0.0])
        for k in range(a, b):
            q = quat_mul(q, dq[k])
        rel_g.append(q)
    rel_g = np.array(rel_g)
    best = np.inf
    for delay in np.arange(0.0, 0.31, 0.05):
        tg = t[idx] + delay
        i = np.clip(np.searchsorted(t, tg, side="right") - 1, 0, t.size - 2)
        u = np.clip((tg - t[i]) / (t[i + 1] - t[i]), 0.0, 1.0)
        q_truth = quat_slerp(s.quat[i], s.quat[i + 1], u)
        rel_t = quat_mul(quat_conj(q_truth[:-1]), q_truth[1:])
        ang = np.linalg.norm(quat_to_rotvec(rel_t), axis=1)
        err = np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(rel_t), rel_g)), axis=1)
        moving = ang > np.deg2rad(5.0)
        best = min(best, float(np.median(err[moving] / ang[moving])))
    return best


@pytest.mark.parametrize("speed,sensor", [("eV50p", "MPU9150"), ("eV50p", "LSM9DS0")])
def test_rasteiro_units_and_truth_convention(data_file, speed, sensor):
    s = load_session(data_file(RASTEIRO.format(speed, sensor)))
    assert s.meta["mag_unit"] == "counts" and s.meta["sensor"] == sensor
    assert np.median(np.linalg.norm(s.acc, axis=1)) == pytest.approx(9.81, abs=0.2)
    assert s.meta["truth_alignment_deg"] < 5.0
    # integrating the converted gyro reproduces the truth's relative rotations (units + convention)
    assert _relative_rotation_error(s) < 0.1


def test_rasteiro_bogus_row_is_dropped(data_file):
    s = load_session(data_file(RASTEIRO.format("V_300", "MPU9150")))
    assert len(s.meta["dropped_rows"]) == 1
    assert np.all(np.diff(s.t) > 0)


# ---------------------------------------------------------------- synthetic round trips

def test_npz_with_rate_and_extra_keys(tmp_path, valid_session):
    path = tmp_path / "s.npz"
    np.savez(path, gyr=valid_session.gyr, acc=valid_session.acc, mag=valid_session.mag, rate=100.0,
             quat=valid_session.quat, note=np.array([1, 2]))
    s = load_session(path)
    np.testing.assert_allclose(s.t, np.arange(valid_session.n) / 100.0)
    np.testing.assert_array_equal(s.quat, valid_session.quat)
    assert s.meta["ignored_keys"] == ["note"]


def test_imugraph_csv_with_missing_mag_cells(tmp_path, valid_session):
    path = tmp_path / "s.csv"
    lines = ["time_s,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z"]
    for k in range(valid_session.n):
        m = ",".join(repr(float(v)) for v in valid_session.mag[k]) if k % 5 == 0 else ",,"
        vals = [valid_session.t[k], *valid_session.gyr[k], *valid_session.acc[k]]
        lines.append(",".join(repr(float(v)) for v in vals) + "," + m)
    path.write_text("\n".join(lines) + "\n")
    s = load_session(path)
    np.testing.assert_array_equal(s.gyr, valid_session.gyr)
    assert s.mag_valid.sum() == len(range(0, valid_session.n, 5))
    np.testing.assert_array_equal(s.mag[::5], valid_session.mag[::5])


def test_xio_style_csv_detected_by_header(tmp_path, valid_session):
    path = tmp_path / "log.csv"
    hdr = ("Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),"
           "Accelerometer Y (g),Accelerometer Z (g),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT)")
    table = np.column_stack([valid_session.t, np.rad2deg(valid_session.gyr), valid_session.acc / G, valid_session.mag])
    np.savetxt(path, table, delimiter=",", header=hdr, comments="", fmt="%.17g")
    s = load_session(path)
    np.testing.assert_allclose(s.gyr, valid_session.gyr, rtol=1e-12)
    np.testing.assert_allclose(s.acc, valid_session.acc, rtol=1e-12)


def test_validate_false_returns_the_raw_reading(tmp_path, valid_session):
    path = tmp_path / "g.npz"
    np.savez(path, gyr=valid_session.gyr, acc=valid_session.acc / G, mag=valid_session.mag, t=valid_session.t)
    s = load_session(path, validate=False)
    assert np.median(np.linalg.norm(s.acc, axis=1)) == pytest.approx(1.0, abs=0.01)


# ---------------------------------------------------------------- writers

def test_calibration_json_round_trip(tmp_path):
    cal = Calibration(D=np.array([[1.1, 0.02, 0.0], [0.0, 0.9, 0.01], [0.0, 0.0, 1.05]]), o=np.array([3.0, -2.0, 0.5]),
                      dip_deg=65.0, gyro_bias=np.array([0.001, -0.002, 0.0]),
                      noise={"gyr": np.array([0.01, 0.01, 0.01])}, std={"o": np.array([0.1, np.nan, 0.1])},
                      coverage={"identifiable": True}, converged=True, iterations=7)
    path = write_calibration_json(tmp_path / "out" / "calibration.json", cal)
    text = path.read_text()
    assert "NaN" not in text and text.startswith("{\n  ")          # strict JSON, indented
    json.loads(text)
    back = read_calibration_json(path)
    np.testing.assert_array_equal(back.D, cal.D)
    np.testing.assert_array_equal(back.o, cal.o)
    assert back.dip_deg == 65.0 and back.converged and back.iterations == 7
    assert np.isnan(back.std["o"][1]) and back.std["o"][0] == 0.1
    assert list(tmp_path.joinpath("out").iterdir()) == [path]       # no temporary left behind


def test_orientation_npz(tmp_path, valid_session):
    path = write_orientation_npz(tmp_path / "orientation.npz", valid_session.t, valid_session.quat)
    with np.load(path) as z:
        assert sorted(z.keys()) == ["quat", "t"]
        np.testing.assert_array_equal(z["quat"], valid_session.quat)
    with pytest.raises(ValueError):
        write_orientation_npz(tmp_path / "bad.npz", valid_session.t, valid_session.quat[:-1])
    assert not (tmp_path / "bad.npz").exists()


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    target = atomic_write_text(tmp_path / "a.txt", "old")

    with pytest.raises(TypeError):
        atomic_write_bytes(target, 12345)                           # not bytes: the write fails
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_writes_get_the_usual_file_mode(tmp_path):
    """mkstemp's 0600 must not leak into result files: they follow the umask like any new file."""
    import os
    from imugraph.io.writers import atomic_write_text
    out = atomic_write_text(tmp_path / "a.txt", "x")
    plain = tmp_path / "b.txt"
    plain.write_text("x")
    assert os.stat(out).st_mode & 0o777 == os.stat(plain).st_mode & 0o777
