"""x-IMU3 body sessions (imugraph.io.xio_body): the real 7-sensor folder, a simulated session written as x-IMU3
CSVs and read back, dropouts, folder names, and `imugraph mocap` on the real folder."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from imugraph.body.skeleton import LOWER_BODY, lower_body
from imugraph.errors import SessionError
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.io.body_session import read_body_session
from imugraph.io.xio_body import read_ximu3_body, segment_of
from imugraph.sim.body import BodyMotion, random_placements, simulate_body
from imugraph.sim.sensors import SensorParams

G = 9.80665
FOLDERS = {"Pelvis": "pelvis 64F0EDBF (UDP)", "LeftUpperLeg": "Left Upper Leg 64F61CC4 (UDP)",
           "LeftLowerLeg": "Left Lower Leg 64F61CB3 (UDP)", "LeftFoot": "Left Foot 64F0EBCE (UDP)",
           "RightUpperLeg": "Right Upper Leg 64F61C2E (UDP)", "RightLowerLeg": "Right Lower Leg 64F61B2A (UDP)",
           "RightFoot": "Right Foot 64F619FB (UDP)"}
T0_US = 917_400_000                    # a synchronised x-IMU3 clock does not start at 0


def _sim(seconds=3.0, rate=50.0):
    skel = lower_body()
    t = np.arange(0, seconds, 1.0 / rate)
    rv = np.zeros((t.size, len(skel.names), 3))
    rv[:, :, 1] = 0.4 * np.sin(2 * np.pi * 0.8 * t)[:, None] * np.linspace(0.2, 1, len(skel.names))
    q = rotmat_to_quat(expmap(rv))
    root = np.column_stack([0.5 * t, 0 * t, 0.9 + 0 * t])
    motion = BodyMotion(t, skel.names, q, skel.forward_kinematics(q, root))
    rng = np.random.default_rng(3)
    params = SensorParams(gyro_noise=0.01, acc_noise=0.05, mag_noise=0.01)
    return simulate_body(motion, skel, random_placements(skel, rng), params, rng, name="sim")


def _write_sensor(folder, stamps_us, gyr_rad, acc_ms2, mag, mag_every=3, quat=None):
    """x-IMU3 export files as the GUI writes them: °/s, g, µs stamps; the magnetometer on its own stamps."""
    folder.mkdir(parents=True)
    rows = [f"{s},{g[0]:.10f},{g[1]:.10f},{g[2]:.10f},{a[0]:.10f},{a[1]:.10f},{a[2]:.10f}"
            for s, g, a in zip(stamps_us, np.rad2deg(gyr_rad), acc_ms2 / G)]
    (folder / "Inertial.csv").write_text("Timestamp (us),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),"
                                         "Accelerometer X (g),Accelerometer Y (g),Accelerometer Z (g)\n"
                                         + "\n".join(rows) + "\n")
    k = np.arange(0, len(stamps_us), mag_every)
    mrows = [f"{stamps_us[i] + 3000},{mag[i, 0]:.10f},{mag[i, 1]:.10f},{mag[i, 2]:.10f}" for i in k]
    (folder / "Magnetometer.csv").write_text("Timestamp (us),X (a.u.),Y (a.u.),Z (a.u.)\n" + "\n".join(mrows) + "\n")
    if quat is not None:
        qrows = [f"{s},{q[0]:.12f},{q[1]:.12f},{q[2]:.12f},{q[3]:.12f}" for s, q in zip(stamps_us, quat)]
        (folder / "Quaternion.csv").write_text("Timestamp (us),W,X,Y,Z\n" + "\n".join(qrows) + "\n")
    return k


def test_simulated_session_round_trip(tmp_path):
    bs = _sim()
    stamps = T0_US + np.round(bs.t * 1e6).astype(np.int64)
    mag_rows = {}
    for seg, s in bs.sensors.items():
        mag_rows[seg] = _write_sensor(tmp_path / "rec" / FOLDERS[seg], stamps, s.gyr, s.acc, s.mag, quat=s.quat)
    (tmp_path / "rec" / "notes").mkdir()                       # a folder without Inertial.csv is not a sensor
    got = read_body_session(tmp_path / "rec")
    assert set(got.sensors) == set(LOWER_BODY) and got.n == bs.n
    assert got.skeleton.names == lower_body().names
    np.testing.assert_allclose(got.t, bs.t, atol=1e-9)
    assert got.rate == pytest.approx(50.0)
    for seg, s in bs.sensors.items():
        g = got.sensors[seg]
        np.testing.assert_allclose(g.t, got.t, atol=0)
        np.testing.assert_allclose(g.gyr, s.gyr, atol=1e-9)                  # °/s → rad/s
        np.testing.assert_allclose(g.acc, s.acc, atol=1e-8)                  # g → m/s²
        np.testing.assert_allclose(g.quat, s.quat, atol=1e-9)
        # the magnetometer on its own stamps (3 ms after an inertial one): on that grid sample, NaN elsewhere
        has = np.all(np.isfinite(g.mag), axis=1)
        assert np.array_equal(np.flatnonzero(has), mag_rows[seg])
        np.testing.assert_allclose(g.mag[has], s.mag[mag_rows[seg]], atol=1e-9)
    assert got.meta["dropouts_total"] == {"count": 0, "missing_samples": 0, "bridged_grid_samples": 0}
    assert got.meta["sensors"]["Pelvis"]["serial"] == "64F0EDBF"


def test_offsets_and_dropouts_bridged_by_interpolation(tmp_path):
    """A sensor 7 ms late with two dropped rows: its linear-in-time gyro is exact on the common grid (X1)."""
    bs = _sim()
    base = T0_US + np.round(bs.t * 1e6).astype(np.int64)
    for seg, s in bs.sensors.items():
        stamps, gyr, acc, mag = base, s.gyr, s.acc, s.mag
        if seg == "RightFoot":
            stamps = base + 7000
            tt = (stamps - T0_US) * 1e-6
            gyr = np.column_stack([0.1 + 0.5 * tt, -0.2 + 0.1 * tt, 0.3 * tt])
            keep = np.ones(base.size, bool)
            keep[[40, 90, 91]] = False                              # one 1-sample and one 2-sample dropout
            stamps, gyr, acc, mag = stamps[keep], gyr[keep], acc[keep], mag[keep]
        _write_sensor(tmp_path / "rec" / FOLDERS[seg], stamps, gyr, acc, mag)
    got = read_ximu3_body(tmp_path / "rec")
    # common span: from the latest first stamp (RightFoot's, 7 ms in) to the earliest last stamp
    assert got.meta["clock"]["start_stamp_s"] == pytest.approx((T0_US + 7000) * 1e-6)
    assert got.n == bs.n - 1
    tt = got.t + 0.007
    np.testing.assert_allclose(got.sensors["RightFoot"].gyr,
                               np.column_stack([0.1 + 0.5 * tt, -0.2 + 0.1 * tt, 0.3 * tt]), atol=1e-9)
    assert np.all(np.isfinite(got.sensors["RightFoot"].acc))
    d = got.meta["dropouts"]["RightFoot"]
    assert d["count"] == 2 and d["missing_samples"] == 3
    assert d["bridged_grid_samples"] == 2 + 3        # grid samples strictly inside the 40 ms and 60 ms steps
    assert got.meta["dropouts"]["Pelvis"]["count"] == 0


def test_long_dropout_refused(tmp_path):
    bs = _sim()
    base = T0_US + np.round(bs.t * 1e6).astype(np.int64)
    for seg, s in bs.sensors.items():
        keep = np.ones(base.size, bool)
        if seg == "LeftLowerLeg":
            keep[60:66] = False                                    # 6 samples (120 ms) never arrived
        _write_sensor(tmp_path / "rec" / FOLDERS[seg], base[keep], s.gyr[keep], s.acc[keep], s.mag[keep])
    with pytest.raises(SessionError) as e:
        read_ximu3_body(tmp_path / "rec")
    msg = str(e.value)
    assert "LeftLowerLeg" in msg and "6 samples" in msg and "≤ 3" in msg
    assert read_ximu3_body(tmp_path / "rec", max_gap_samples=6).meta["dropouts"]["LeftLowerLeg"]["missing_samples"] == 6


def test_unknown_folder_name(tmp_path):
    bs = _sim()
    stamps = T0_US + np.round(bs.t * 1e6).astype(np.int64)
    for seg, s in bs.sensors.items():
        name = "Left Elbow 64F61CC4 (UDP)" if seg == "LeftUpperLeg" else FOLDERS[seg]
        _write_sensor(tmp_path / "rec" / name, stamps, s.gyr, s.acc, s.mag)
    with pytest.raises(SessionError) as e:
        read_body_session(tmp_path / "rec")
    assert e.value.field == "folder name" and "Left Elbow" in str(e.value) and "LeftUpperLeg" in str(e.value)


def test_segment_names():
    assert segment_of("pelvis 64F0EDBF (UDP)") == ("Pelvis", "64F0EDBF")
    assert segment_of("Left Upper Leg 64F61CC4 (UDP)") == ("LeftUpperLeg", "64F61CC4")
    assert segment_of("RIGHT_FOOT") == ("RightFoot", None)
    assert segment_of("Right Toe 64F619FB (UDP)")[0] is None


def _raw_stamps(folder):
    return np.loadtxt(folder / "Inertial.csv", delimiter=",", skiprows=1, usecols=0) * 1e-6


def test_real_folder(data_file):
    root = data_file("xio_lower_body")
    bs = read_body_session(root)
    assert set(bs.sensors) == set(LOWER_BODY)
    raw = {seg: _raw_stamps(root / name) for seg, name in FOLDERS.items()}
    t_a = max(r[0] for r in raw.values())
    t_b = min(r[-1] for r in raw.values())
    assert bs.meta["clock"]["start_stamp_s"] == pytest.approx(t_a)
    assert bs.meta["clock"]["first_stamp_spread_ms"] < 20.0        # one synchronised clock
    assert bs.t[0] == 0.0 and bs.t[-1] <= t_b - t_a + 1e-9 and bs.t[-1] > t_b - t_a - 0.021
    dt = np.diff(bs.t)
    assert np.ptp(dt) < 1e-9 and 49.5 < bs.rate < 50.5          # one uniform grid at the sensors' ~50 Hz
    rest = bs.t < 0.8                                            # standing still before the motion (≈ 1.2 s)
    for seg, s in bs.sensors.items():
        assert s.gyr.shape == s.acc.shape == s.mag.shape == (bs.n, 3)
        assert np.array_equal(s.t, bs.t)
        assert np.all(np.isfinite(s.gyr)) and np.all(np.isfinite(s.acc))
        assert abs(np.linalg.norm(s.acc[rest], axis=1).mean() - 9.81) < 0.1           # m/s², not g
        assert np.abs(s.gyr[rest]).max() < 0.1                                        # rad/s at rest, not °/s
        assert 3.0 < np.abs(s.gyr).max() < 35.0                                       # rad/s while moving
        assert 300 < np.sum(np.all(np.isfinite(s.mag), axis=1)) < 400                 # ~20 Hz over 18.6 s
        # dropouts: stamp steps over 1.5 median steps inside the common span, counted from the file here
        r = raw[seg]
        d = np.diff(r)
        med = np.median(d)
        gap = (d > 1.5 * med) & (r[1:] > t_a) & (r[:-1] < t_b)
        assert bs.meta["dropouts"][seg]["count"] == int(gap.sum()) > 0
        assert bs.meta["dropouts"][seg]["missing_samples"] == int(np.sum(np.round(d[gap] / med) - 1))
    assert bs.meta["dropouts_total"]["count"] == 124


def test_mocap_runs_on_the_real_folder(data_file, tmp_path, capsys):
    from imugraph.commands.mocap import add_arguments, run_mocap

    data_file("xio_lower_body")
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["xio_lower_body", "--out", str(tmp_path / "m"), "--quiet",
                         "--data-dir", str(data_file("xio_lower_body").parent)])
    assert run_mocap(args) == 0
    info = json.loads((tmp_path / "m" / "mocap_info.json").read_text())
    assert info["samples"] == 928 and info["info"]["npose"] == "detected"
    a = np.genfromtxt(tmp_path / "m" / "joint_angles.csv", delimiter=",", names=True)
    for side in ("Left", "Right"):
        knee = a[f"{side}Knee_flexion"]
        assert np.all(np.isfinite(knee)) and 60.0 < knee.max() < 160.0 and knee.min() > -15.0   # plausible range


def test_cubic_interpolation_option(tmp_path):
    """interp='cubic' reproduces a quadratic-in-time gyro exactly across a dropout and a clock offset; linear
    (the default) does not; an unknown name is refused."""
    bs = _sim()
    base = T0_US + np.round(bs.t * 1e6).astype(np.int64)
    for seg, s in bs.sensors.items():
        stamps, gyr = base, s.gyr
        if seg == "LeftFoot":
            stamps = base + 9000
            tt = (stamps - T0_US) * 1e-6
            gyr = np.column_stack([0.5 * tt ** 2 - tt, 0.2 + 0.1 * tt ** 2, -0.3 * tt ** 2])
        keep = np.ones(stamps.size, bool)
        keep[[50, 51]] = False if seg == "LeftFoot" else True
        _write_sensor(tmp_path / "rec" / FOLDERS[seg], stamps[keep], gyr[keep], s.acc[keep], s.mag[keep])
    tt = read_ximu3_body(tmp_path / "rec").t + 0.009
    want = np.column_stack([0.5 * tt ** 2 - tt, 0.2 + 0.1 * tt ** 2, -0.3 * tt ** 2])
    cubic = read_ximu3_body(tmp_path / "rec", interp="cubic")
    np.testing.assert_allclose(cubic.sensors["LeftFoot"].gyr, want, atol=1e-8)
    assert cubic.meta["interpolation"].startswith("cubic")
    linear = read_ximu3_body(tmp_path / "rec")
    assert np.abs(linear.sensors["LeftFoot"].gyr - want).max() > 1e-4
    with pytest.raises(SessionError):
        read_ximu3_body(tmp_path / "rec", interp="spline")
