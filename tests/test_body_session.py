"""Multi-IMU sessions: own folder format round trip, gaittoolbox MTw + Vicon readers, MVNX reader."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imugraph.body.skeleton import lower_body
from imugraph.errors import SessionError
from imugraph.geometry import expmap, quat_to_rotmat, rotmat_to_quat
from imugraph.io.body_session import (BodySession, read_body_session, read_gaittoolbox_vicon, read_mvnx,
                                      write_body_session)
from imugraph.sim.body import BodyMotion, random_placements, simulate_body
from imugraph.sim.sensors import SensorParams


def _sim(seed=0, seconds=3.0):
    skel = lower_body()
    t = np.arange(0, seconds, 0.01)
    rv = np.zeros((t.size, len(skel.names), 3))
    rv[:, :, 1] = 0.4 * np.sin(2 * np.pi * 0.8 * t)[:, None] * np.linspace(0.2, 1, len(skel.names))
    q = rotmat_to_quat(expmap(rv))
    root = np.column_stack([0.5 * t, 0 * t, 0.9 + 0 * t])
    motion = BodyMotion(t, skel.names, q, skel.forward_kinematics(q, root))
    rng = np.random.default_rng(seed)
    params = SensorParams(gyro_noise=0.01, acc_noise=0.05, mag_noise=0.01)
    bs = simulate_body(motion, skel, random_placements(skel, rng), params, rng, name="walkish")
    return skel, bs


def test_own_format_round_trip(tmp_path):
    skel, bs = _sim()
    folder = write_body_session(tmp_path / "sess", bs)
    doc = json.loads((folder / "session.json").read_text())
    assert doc["format"] == "imugraph-body" and set(doc["sensors"]) == set(skel.sensed)
    back = read_body_session(folder)
    assert isinstance(back, BodySession) and back.name == "walkish"
    assert np.allclose(back.t, bs.t)
    for seg, s in bs.sensors.items():
        b = back.sensors[seg]
        for field in ("gyr", "acc", "mag", "quat"):
            assert np.array_equal(getattr(b, field), getattr(s, field)), (seg, field)
    assert back.skeleton.names == skel.names and np.allclose(back.skeleton.offsets, skel.offsets)
    assert back.skeleton.sensed == skel.sensed and np.allclose(back.skeleton.ends, skel.ends)
    for key in ("n_quat", "n_pos"):
        assert np.array_equal(back.truth[key], bs.truth[key])
    for seg, pl in bs.truth["placements"].items():
        assert np.array_equal(back.truth["placements"][seg]["bRs"], pl["bRs"])
        assert np.array_equal(back.truth["sensor_pos"][seg], bs.truth["sensor_pos"][seg])
    part = back.slice(10, 60)
    assert part.n == 50 and part.truth["n_quat"].shape[0] == 50 and part.sensors["Pelvis"].n == 50
    assert not list(folder.glob("*.tmp"))


def test_own_format_errors(tmp_path):
    with pytest.raises(SessionError):
        read_body_session(tmp_path)                                   # empty folder: not a session
    _, bs = _sim()
    folder = write_body_session(tmp_path / "s", bs)
    doc = json.loads((folder / "session.json").read_text())
    (folder / "session.json").write_text(json.dumps({**doc, "format": "other"}))
    with pytest.raises(SessionError) as e:
        read_body_session(folder)
    assert e.value.field == "format"
    short = bs.sensors["Pelvis"].slice(0, 200)
    np.savez(folder / "Pelvis.npz", t=short.t, gyr=short.gyr, acc=short.acc, mag=short.mag)
    (folder / "session.json").write_text(json.dumps(doc))
    with pytest.raises(SessionError) as e:
        read_body_session(folder)
    assert e.value.field == "t"
    (folder / "session.json").write_text("{not json")
    with pytest.raises(SessionError):
        read_body_session(folder)


def test_gaittoolbox_rawimu(data_file):
    bs = read_body_session(data_file("gaittoolbox/rawimu"))
    assert set(bs.sensors) == set(lower_body().names) and bs.n == 2503
    assert bs.rate == pytest.approx(100.0)
    assert bs.sensors["LeftFoot"].meta["sensor_id"] == "00B40C55"
    for s in bs.sensors.values():
        assert np.allclose(s.t, bs.t)
        assert abs(np.linalg.norm(s.acc[:50].mean(0)) - 9.8) < 0.3    # standing still at the start
    # the feet move more than the pelvis while walking
    assert np.std(bs.sensors["RightFoot"].gyr) > 2 * np.std(bs.sensors["Pelvis"].gyr)


def test_gaittoolbox_vicon(data_file):
    v = read_gaittoolbox_vicon(data_file("gaittoolbox/vicon/S02-Trial-Walk-1.csv"))
    assert v["imu_index"][0] == 1119 and v["imu_index"][-1] == 2073 and v["t"].size == 955
    assert set(v["quat"]) == set(lower_body().names)
    for q in v["quat"].values():
        assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    thigh = np.linalg.norm(v["joints"]["RFEP"] - v["joints"]["RFEO"], axis=1)
    assert 0.3 < thigh.mean() < 0.5 and thigh.std() < 0.01            # a rigid thigh
    assert np.all(v["joints"]["PELV"][:, 2] > v["joints"]["RTIO"][:, 2] + 0.5)   # z up


def _mvnx_text(t_ms, seg_q, seg_p, s_q, free, mag, ns=True):
    """A small MVNX document: 2 segments (Pelvis → RightUpperLeg), 2 sensors, reference + normal frames."""
    fmt = lambda a: " ".join(f"{v:.9f}" for v in np.ravel(a))
    frames = ['<frame time="0" index="" type="identity"><orientation>1 0 0 0 1 0 0 0</orientation></frame>']
    for k, tk in enumerate(t_ms):
        frames.append(f'<frame time="{tk}" index="{k}" type="normal"><orientation>{fmt(seg_q[k])}</orientation>'
                      f'<position>{fmt(seg_p[k])}</position><sensorFreeAcceleration>{fmt(free[k])}'
                      f'</sensorFreeAcceleration><sensorMagneticField>{fmt(mag[k])}</sensorMagneticField>'
                      f'<sensorOrientation>{fmt(s_q[k])}</sensorOrientation></frame>')
    xmlns = ' xmlns="http://www.xsens.com/mvn/mvnx"' if ns else ""
    return (f'<?xml version="1.0"?><mvnx version="4"{xmlns}><subject label="x" frameRate="100" segmentCount="2">'
            '<segments><segment label="Pelvis" id="1"><points><point label="pHipOrigin"><pos_b>0 0 0</pos_b></point>'
            '<point label="jRightHip"><pos_b>0 -0.08 0</pos_b></point></points></segment>'
            '<segment label="RightUpperLeg" id="2"><points><point label="jRightHip"><pos_b>0 0 0</pos_b></point>'
            '<point label="jRightKnee"><pos_b>0 0 -0.42</pos_b></point></points></segment></segments>'
            '<sensors><sensor label="Pelvis"/><sensor label="RightUpperLeg"/></sensors>'
            '<joints><joint label="jRightHip"><connector1>Pelvis/jRightHip</connector1>'
            '<connector2>RightUpperLeg/jRightHip</connector2></joint></joints>'
            f'<frames segmentCount="2" sensorCount="2">{"".join(frames)}</frames></subject></mvnx>')


@pytest.mark.parametrize("ns", [True, False])
def test_mvnx_synthetic(tmp_path, ns):
    n, dt = 40, 0.01
    t_ms = np.round(np.arange(n) * dt * 1000).astype(int)
    w = np.array([[0.0, 0.0, 1.5], [0.4, -0.3, 0.0]])              # constant sensor rates, rad/s (sensor frame)
    s_q = np.stack([rotmat_to_quat(expmap(np.outer(np.arange(n) * dt, wi))) for wi in w], 1)
    free = np.zeros((n, 2, 3))
    free[:, 1] = [0.5, -1.0, 2.0]
    mag = np.tile([0.3, 0.0, -0.5], (n, 2, 1))
    seg_q, seg_p = s_q.copy(), np.zeros((n, 2, 3))
    seg_p[:, 1] = [0, -0.08, 0]
    path = tmp_path / "trial.mvnx"
    path.write_text(_mvnx_text(t_ms, seg_q, seg_p, s_q, free, mag, ns))
    bs = read_body_session(path)
    assert bs.n == n and np.allclose(bs.t, np.arange(n) * dt) and set(bs.sensors) == {"Pelvis", "RightUpperLeg"}
    for i, name in enumerate(("Pelvis", "RightUpperLeg")):
        s = bs.sensors[name]
        assert np.allclose(s.gyr, w[i], atol=1e-6)
        # specific force in the sensor frame: nRsᵀ (free − [0, 0, −g])
        expect = np.einsum("tba,tb->ta", quat_to_rotmat(s_q[:, i]), free[:, i] + [0, 0, 9.81])
        assert np.allclose(s.acc, expect, atol=1e-6)
        assert np.allclose(s.mag, mag[:, i]) and np.allclose(s.quat, s_q[:, i], atol=1e-8)
    assert bs.skeleton.names == ("Pelvis", "RightUpperLeg") and np.allclose(bs.skeleton.offsets[1], [0, -0.08, 0])
    assert np.allclose(bs.skeleton.ends[1], [0, 0, -0.42])
    assert np.allclose(bs.truth["n_pos"], seg_p)
    assert read_mvnx(path).name == "trial"


def test_mvnx_errors(tmp_path):
    p = tmp_path / "bad.mvnx"
    p.write_text("<mvnx><subject")
    with pytest.raises(SessionError):
        read_mvnx(p)
    n = 5
    q = np.tile([1.0, 0, 0, 0], (n, 2, 1))
    text = _mvnx_text(np.arange(n) * 10, q, np.zeros((n, 2, 3)), q, np.zeros((n, 2, 3)), np.zeros((n, 2, 3)))
    p.write_text(text.replace("<sensorMagneticField>0.000000000 ", "<sensorMagneticField>", 1))
    with pytest.raises(SessionError) as e:
        read_mvnx(p)
    assert "sensorMagneticField" in e.value.field


def test_folder_without_skeleton_gets_the_nominal_lower_body(tmp_path):
    """session.json with "skeleton": null and the 7 lower-body sensors → lower_body(1.75); other sets → clear error."""
    import json
    from imugraph.body.skeleton import LOWER_BODY
    from imugraph.errors import SessionError
    from imugraph.io.body_session import read_body_session
    n = 200
    t = np.arange(n) / 50.0
    files = {}
    rng = np.random.default_rng(0)
    for seg in LOWER_BODY:                      # a sensor at rest with noise (a constant signal looks clipped)
        e = 0.01 * rng.standard_normal((3, n, 3))
        np.savez(tmp_path / f"{seg}.npz", t=t, gyr=e[0], acc=[0, 0, 9.81] + e[1], mag=[0.4, 0.0, -0.9] + e[2])
        files[seg] = f"{seg}.npz"
    doc = {"format": "imugraph-body", "version": 1, "name": "x", "sensors": files, "skeleton": None}
    (tmp_path / "session.json").write_text(json.dumps(doc))
    s = read_body_session(tmp_path)
    assert s.skeleton is not None and set(s.skeleton.names) == set(LOWER_BODY)
    doc["sensors"] = {k: v for k, v in list(files.items())[:3]}
    (tmp_path / "session.json").write_text(json.dumps(doc))
    with pytest.raises(SessionError, match="skeleton"):
        read_body_session(tmp_path)
