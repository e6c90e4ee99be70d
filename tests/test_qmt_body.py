"""The qmt full-body .mat (imugraph.io.qmt_body): the real file's units and quaternion convention, the segment
mapping, bad input, and a short `imugraph mocap` run through the CLI on the first 10 s."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io

from imugraph.body.skeleton import LOWER_BODY, tie_rules
from imugraph.errors import SessionError
from imugraph.geometry import integrate_gyro, quat_angle, quat_conj, quat_to_rotmat
from imugraph.io.body_session import read_body_session
from imugraph.io.qmt_body import LOWER_BODY_SENSORS, SEGMENTS, fit_quat_frame, is_qmt_body_mat, read_qmt_body

REL = "qmt_full_body/full_body_example_data.mat"
REST = slice(0, 300)              # the subject stands still for the first ~4.5 s (median |gyr| < 0.05 rad/s)


@pytest.fixture(scope="module")
def qmt(data_file):
    return read_body_session(data_file(REL))


def test_reader_on_the_real_file(qmt):
    assert qmt.n == 10000 and abs(qmt.rate - 100.0) < 1e-6 and qmt.t[0] == pytest.approx(40.0)
    assert set(qmt.sensors) == set(SEGMENTS.values()) and len(qmt.sensors) == 16
    sk = qmt.skeleton
    assert set(sk.sensed) == set(qmt.sensors) and "L5" in sk.sensed
    assert "RightShoulder" not in sk.sensed and "LeftShoulder" not in sk.sensed
    rules = tie_rules(sk, sk.sensed)
    assert not set(rules) & set(sk.sensed)                        # no sensed segment is tied
    assert rules["RightShoulder"] == ("T8", "RightUpperArm", 0.5)
    assert rules["L3"] == ("L5", "T8", pytest.approx(1 / 3)) and rules["T12"] == ("L5", "T8", pytest.approx(2 / 3))
    for s in qmt.sensors.values():
        assert np.all(np.isnan(s.mag)) and np.all(np.isfinite(s.gyr)) and np.all(np.isfinite(s.acc))


def test_units_are_si(qmt):
    """m/s² (|acc| ≈ 9.8 at rest, not 1) and rad/s (rest noise a few mrad/s, peaks of several rad/s)."""
    for seg, s in qmt.sensors.items():
        a = np.linalg.norm(s.acc[REST], axis=1)
        assert 9.5 < np.median(a) < 10.4, seg
        assert np.median(np.linalg.norm(s.gyr[REST], axis=1)) < 0.05, seg
        assert np.max(np.linalg.norm(s.gyr, axis=1)) > 3.0, seg        # real motion in rad/s, not 0.05 "°/s"


def test_quat_is_sensor_to_nav_z_up(qmt):
    """(Q2): nRs·acc at rest is +g ẑ; and the gyroscope integrated from the quat over 1 s lands on the quat
    1 s later (q_k = q_{k−1} ⊗ Exp(ω dt), sensor→nav). Both fail for scalar-last or the inverse rotation."""
    right, wrong = [], []
    for seg, s in qmt.sensors.items():
        up = np.einsum("nij,nj->ni", quat_to_rotmat(s.quat[REST]), s.acc[REST]).mean(axis=0)
        assert np.degrees(np.arccos(up[2] / np.linalg.norm(up))) < 2.5, seg
        for k0 in (1000, 5000, 8000):
            w, dt = s.gyr[k0 + 1:k0 + 102], np.full(101, 0.01)
            q = integrate_gyro(w, dt, s.quat[k0])                                  # q ⊗ Exp(ω dt): sensor→nav
            q_nav = quat_conj(integrate_gyro(-w, dt, quat_conj(s.quat[k0])))      # Exp(ω dt) ⊗ q: nav→sensor
            right.append(np.degrees(quat_angle(q[-1], s.quat[k0 + 100])))
            wrong.append(np.degrees(quat_angle(q_nav[-1], s.quat[k0 + 100])))
            assert right[-1] < 4.0, (seg, k0)
    assert sum(right) < 0.1 * sum(wrong)


def test_quat_fit_rejects_wrong_conventions(data_file):
    """The (Q1) fit on the file's raw quaternion: scalar first fits the gyro far better than scalar last."""
    m = scipy.io.loadmat(data_file(REL))
    for name in ("hip", "lower_leg_left", "hand_right"):
        rec = m[name][0, 0]
        _, res_wxyz, _ = fit_quat_frame(rec["quat"], rec["gyr"], 0.01)
        _, res_xyzw, _ = fit_quat_frame(np.roll(rec["quat"], 1, axis=1), rec["gyr"], 0.01)
        assert res_wxyz < 0.1 and res_xyzw > 3 * res_wxyz, name


def _small_mat(path, n=300, drop=None, reshape=None, no_t=False):
    rng = np.random.default_rng(0)
    t = 40.0 + 0.01 * np.arange(n)
    doc = {} if no_t else {"t": t[:, None]}
    for name in ("hip", "upper_leg_right"):
        st = {"acc": np.tile([0.0, 0.0, 9.81], (n, 1)) + 0.02 * rng.standard_normal((n, 3)),
              "gyr": 0.01 * rng.standard_normal((n, 3)), "quat": np.tile([1.0, 0, 0, 0], (n, 1))}
        if name == "hip" and drop:
            del st[drop]
        if name == "hip" and reshape:
            st[reshape] = st[reshape][:, :2]
        doc[name] = st
    scipy.io.savemat(path, doc)
    return path


def test_bad_input_names_the_field(tmp_path):
    p = _small_mat(tmp_path / "nogyr.mat", drop="gyr")
    assert is_qmt_body_mat(p)
    with pytest.raises(SessionError) as e:
        read_body_session(p)
    assert e.value.field == "hip.gyr" and "missing" in e.value.found
    with pytest.raises(SessionError) as e:
        read_qmt_body(_small_mat(tmp_path / "shape.mat", reshape="acc"))
    assert e.value.field == "hip.acc" and "(300, 2)" in e.value.found
    with pytest.raises(SessionError) as e:
        read_qmt_body(_small_mat(tmp_path / "not.mat", no_t=True))
    assert e.value.field == "t"
    with pytest.raises(SessionError) as e:
        read_qmt_body(_small_mat(tmp_path / "ok.mat"), sensors=["upper_leg_right"])
    assert e.value.field == "hip"
    with pytest.raises(SessionError) as e:
        read_qmt_body(_small_mat(tmp_path / "ok2.mat"), sensors=["hip", "tail"])
    assert e.value.field == "sensors" and "tail" in e.value.found
    (tmp_path / "text.mat").write_text("not a mat file")
    assert not is_qmt_body_mat(tmp_path / "text.mat")
    with pytest.raises(SessionError):
        read_body_session(tmp_path / "text.mat")


def test_lower_body_subset(data_file):
    lb = read_qmt_body(data_file(REL), sensors=LOWER_BODY_SENSORS)
    assert set(lb.sensors) == set(LOWER_BODY) and tuple(lb.skeleton.names) == LOWER_BODY


def test_mocap_cli_first_10_s(data_file, tmp_path):
    """`imugraph mocap` on the file cut to its first 10 s (N-pose until 44.5 s, then the subject starts to move);
    the N-pose given (--npose): the detection finds no common rest (the upper-arm sensors read 0.04 rad/s)."""
    from imugraph import cli

    m = scipy.io.loadmat(data_file(REL))
    n = 1000
    doc = {"t": m["t"][:n]}
    for name in SEGMENTS:
        rec = m[name][0, 0]
        doc[name] = {k: rec[k][:n] for k in ("acc", "gyr", "quat")}
    src = tmp_path / "qmt10.mat"
    scipy.io.savemat(src, doc)
    out = tmp_path / "out"
    assert cli.main(["mocap", str(src), "--out", str(out), "--quiet", "--npose", "40,44"]) == 0
    for f in ("mocap.npz", "joint_angles.csv", "motion.bvh", "joint_angles.png", "stick_figures.png",
              "mocap_info.json"):
        assert (out / f).is_file(), f
    z = np.load(out / "mocap.npz")
    assert z["quat"].shape == (n, 23, 4) and np.all(np.isfinite(z["quat"])) and np.all(np.isfinite(z["pos"]))
    info = json.loads((out / "mocap_info.json").read_text())
    assert info["info"]["npose"] == "given" and set(info["placements"]) == set(SEGMENTS.values())
    names = list(z["segments"])
    knee = quat_angle(z["quat"][:, names.index("RightUpperLeg")], z["quat"][:, names.index("RightLowerLeg")])
    assert np.degrees(np.max(knee)) < 160.0                      # no broken knee
    assert np.degrees(np.median(knee[:300])) < 15.0              # the N-pose stands straight


def test_npose_option():
    from imugraph.commands.mocap import npose_window

    assert npose_window(None) is None and npose_window("40,44") == (40.0, 44.0)
    for bad in ("44,40", "40", "a,b"):
        with pytest.raises(SessionError) as e:
            npose_window(bad)
        assert e.value.source == "--npose"
