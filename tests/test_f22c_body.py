"""Session 22, helper F22c: body-session folders and the --skeleton BVH lookup (U22 defects 5, 7, 8, 11, 15).

(5) sensors without magnetometer (no 'mag' key, or all NaN) read and run through mocap without --mag; --mag is
refused with one line. (7) a simulated session whose gyro exceeds the real-data range (segment rates add up
along the chain) reads back; a changed file or a real-data folder is still checked. (8) one NPZ for two
segments, a segment name the skeleton does not have: refused at read time, naming the valid names. (15) a key
given twice in session.json refused. (11) `bvh:PATH` looked up in the data directory like a session path.
All inputs are simulated in tmp_path; nothing is written into ../shared.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from imugraph.body.skeleton import LOWER_BODY, lower_body, skeleton_from_spec
from imugraph.errors import SessionError
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.io.body_session import read_body_session, write_body_session


def _motion(spin_rad_s: float = 0.0):
    """4 s lower-body motion at 60 Hz (tests/test_mocap_cli.py's), optionally the left foot spinning about its
    z axis at `spin_rad_s` for 0.3 s from t = 2 s (a rate above the 35 rad/s of any real MEMS gyroscope; short,
    so that the centripetal acceleration leaves the median |acc| alone)."""
    from imugraph.sim.body import BodyMotion

    skel = lower_body()
    rate, T = 60.0, 240
    t = np.arange(T) / rate
    env = np.clip((t - 1.5) / 1.0, 0, 1) ** 2
    R = np.zeros((T, len(skel.names), 3, 3))
    R[:, 0] = expmap(np.stack([0.05 * env * np.sin(2 * t), 0.05 * env * np.sin(3 * t), 0.3 * env * np.sin(t)], -1))
    for i in range(1, len(skel.names)):
        w = np.stack([0.1 * np.sin(1.7 * t + i), 0.5 * np.sin(2.5 * t + 0.7 * i), 0.1 * np.sin(1.3 * t)], -1)
        R[:, i] = R[:, skel.parents[i]] @ expmap(env[:, None] * w)
    if spin_rad_s:
        i = skel.index("LeftFoot")
        angle = spin_rad_s * np.clip(t - 2.0, 0.0, 0.3)                # ω = spin_rad_s about the foot's z
        R[:, i] = R[:, i] @ expmap(np.stack([0 * t, 0 * t, angle], -1))
    q = rotmat_to_quat(R)
    root = np.stack([0.2 * env * np.sin(t), 0.1 * env * np.sin(0.7 * t), 0.93 + 0 * t], -1)
    return skel, BodyMotion(t=t, names=skel.names, n_quat=q, n_pos=skel.forward_kinematics(q, root))


def _simulated(folder, spin_rad_s: float = 0.0):
    from imugraph.sim.body import random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    skel, motion = _motion(spin_rad_s)
    rng = np.random.default_rng(0)
    prm = SensorParams(gyro_noise=np.full(3, 0.003), acc_noise=np.full(3, 0.03), mag_noise=np.full(3, 0.01))
    session = simulate_body(motion, skel, random_placements(skel, rng, max_angle_deg=20), prm, rng, name="mini")
    return write_body_session(folder, session), session


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    folder, _ = _simulated(tmp_path_factory.mktemp("f22c") / "mini")
    return folder


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def _rewrite_npz(path, drop=(), **replace):
    z = dict(np.load(path))
    for k in drop:
        z.pop(k)
    z.update(replace)
    np.savez(path, **z)


def _edit_json(folder, fn):
    doc = json.loads((folder / "session.json").read_text())
    fn(doc)
    (folder / "session.json").write_text(json.dumps(doc))


# ---- (5) six-axis body sensors -------------------------------------------------------------------------------

def test_sensors_without_mag_key_read_with_nan_mag(mini, tmp_path):
    folder = _copy(mini, tmp_path / "nomag")
    for seg in LOWER_BODY:
        _rewrite_npz(folder / f"{seg}.npz", drop=("mag",))
    s = read_body_session(folder)
    assert sorted(s.meta["no_mag"]) == sorted(LOWER_BODY)
    assert all(np.isnan(x.mag).all() and x.mag.shape == (x.n, 3) for x in s.sensors.values())
    ref = read_body_session(mini)
    for seg in LOWER_BODY:                                          # everything else as read from the full files
        assert np.array_equal(s.sensors[seg].gyr, ref.sensors[seg].gyr)
    assert "no_mag" not in ref.meta


def test_all_nan_mag_reads_but_inf_still_refused(mini, tmp_path):
    folder = _copy(mini, tmp_path / "nanmag")
    n = read_body_session(mini).n
    _rewrite_npz(folder / "Pelvis.npz", mag=np.full((n, 3), np.nan))
    assert read_body_session(folder).meta["no_mag"] == ["Pelvis"]
    _rewrite_npz(folder / "Pelvis.npz", mag=np.full((n, 3), np.inf))
    with pytest.raises(SessionError, match="inf"):
        read_body_session(folder)


def test_single_imu_npz_still_needs_mag(tmp_path):
    from imugraph.io.readers import read_npz

    p = tmp_path / "six.npz"
    np.savez(p, gyr=np.zeros((60, 3)), acc=np.ones((60, 3)), rate=100.0)
    with pytest.raises(SessionError, match="'mag': found missing"):
        read_npz(p)
    assert np.isnan(read_npz(p, mag_optional=True).mag).all()


def test_mocap_runs_without_mag_and_refuses_mag(mini, tmp_path, capsys):
    from imugraph.cli import main

    folder = _copy(mini, tmp_path / "nomag")
    for seg in LOWER_BODY:
        _rewrite_npz(folder / f"{seg}.npz", drop=("mag",))
    out = tmp_path / "out_mag"
    assert main(["mocap", str(folder), "--mag", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "field 'mag'" in err[0] and "omit --mag" in err[0] and "Pelvis" in err[0]
    assert not out.exists()
    out = tmp_path / "out"
    assert main(["mocap", str(folder), "--out", str(out), "--quiet"]) == 0
    z = np.load(out / "mocap.npz")
    assert z["quat"].shape == (240, 7, 4) and np.isfinite(z["quat"]).all()


# ---- (7) simulated session round trip --------------------------------------------------------------------------

def test_simulated_fast_gyro_reads_back_and_tampering_is_caught(tmp_path):
    from imugraph.io.body_session import gyr_robust_max

    folder, session = _simulated(tmp_path / "fast", spin_rad_s=38.0)
    assert gyr_robust_max(session.sensors["LeftFoot"].gyr) > 35.0            # beyond the real-data limit
    back = read_body_session(folder)
    for seg, s in session.sensors.items():
        assert np.array_equal(back.sensors[seg].gyr, s.gyr) and np.array_equal(back.sensors[seg].mag, s.mag)
    # the same file changed after writing: checked as real data again
    bad = _copy(folder, tmp_path / "tampered")
    _rewrite_npz(bad / "LeftFoot.npz", gyr=session.sensors["LeftFoot"].gyr * 1.001)
    with pytest.raises(SessionError, match="LeftFoot.npz: field 'gyr'.*deg/s"):
        read_body_session(bad)
    # a real-data folder (not simulated) with the same numbers: the units check as before
    real = _copy(folder, tmp_path / "real")
    _edit_json(real, lambda d: d["meta"].pop("simulated"))
    with pytest.raises(SessionError, match="LeftFoot.npz: field 'gyr'.*deg/s"):
        read_body_session(real)


def test_written_statistic_only_for_simulated(mini):
    doc = json.loads((mini / "session.json").read_text())
    assert doc["meta"]["simulated"] is True and set(doc["gyr_robust_max"]) == set(LOWER_BODY)


@pytest.mark.skipif(not __import__("imugraph.config", fromlist=["x"]).data_dir().joinpath(
    "cmu_bvh").is_dir(), reason="../shared/data/cmu_bvh absent")
def test_cmu131_01_benchmark_session_reads_back(tmp_path):
    """U22's case: benchmarks/body_bench.simulated_session('cmu131_01') (RightHand 36.41 rad/s)."""
    from benchmarks.body_bench import simulated_session

    _, ses, _ = simulated_session("cmu131_01", seed=0, duration_s=20.0)
    back = read_body_session(write_body_session(tmp_path / "cmu", ses))
    assert len(back.sensors) == 17
    assert np.array_equal(back.sensors["RightHand"].gyr, ses.sensors["RightHand"].gyr)


# ---- (8) and (15) folder checks --------------------------------------------------------------------------------

def test_one_file_for_two_segments_refused(mini, tmp_path):
    folder = _copy(mini, tmp_path / "dup")
    _edit_json(folder, lambda d: d["sensors"].update(RightUpperLeg="Pelvis.npz"))
    with pytest.raises(SessionError, match="sensors.RightUpperLeg.*Pelvis.npz.*'Pelvis' too.*one NPZ file per"):
        read_body_session(folder)
    folder = _copy(mini, tmp_path / "dup2")                              # the same file by another spelling
    _edit_json(folder, lambda d: d["sensors"].update(RightUpperLeg="./Pelvis.npz"))
    with pytest.raises(SessionError, match="one NPZ file per segment"):
        read_body_session(folder)


def test_unknown_segment_refused_naming_the_valid_ones(mini, tmp_path):
    folder = _copy(mini, tmp_path / "badseg")
    _edit_json(folder, lambda d: d["sensors"].update(LeftKnee=d["sensors"].pop("LeftLowerLeg")))
    (folder / "LeftLowerLeg.npz").unlink()             # refused from session.json alone, before any sensor file
    with pytest.raises(SessionError) as exc:
        read_body_session(folder)
    assert exc.value.field == "sensors" and "LeftKnee" in exc.value.found
    assert all(n in exc.value.expected for n in LOWER_BODY)


def test_sensed_segment_without_file_refused(mini, tmp_path):
    folder = _copy(mini, tmp_path / "fewer")
    _edit_json(folder, lambda d: d["sensors"].pop("RightFoot"))
    with pytest.raises(SessionError, match="no sensor file for the sensed segment.*RightFoot"):
        read_body_session(folder)


def test_duplicate_json_key_refused(mini, tmp_path):
    folder = _copy(mini, tmp_path / "dupkey")
    text = (folder / "session.json").read_text()
    (folder / "session.json").write_text(text.replace('"sensors": {', '"sensors": {"Pelvis": "RightFoot.npz", ', 1))
    with pytest.raises(SessionError, match="field 'Pelvis': found the key twice"):
        read_body_session(folder)


# ---- (11) bvh:PATH in the data directory -----------------------------------------------------------------------

_LEG = ("JOINT {s}Hip\n{{\nOFFSET {x} 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\nJOINT {s}Knee\n{{\n"
        "OFFSET 0 -45 0\nCHANNELS 3 Zrotation Xrotation Yrotation\nJOINT {s}Ankle\n{{\nOFFSET 0 -40 0\n"
        "CHANNELS 3 Zrotation Xrotation Yrotation\nJOINT {s}Toe\n{{\nOFFSET 0 -7 15\n"
        "CHANNELS 3 Zrotation Xrotation Yrotation\nEnd Site\n{{\nOFFSET 0 -1 6\n}}\n}}\n}}\n}}\n}}\n")


def _bvh(path):
    """A centimetre lower body with Xsens MVN joint names (tests/test_skeleton_spec.py's), 2 frames."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS 6 Xposition Yposition Zposition Zrotation "
                    "Xrotation Yrotation\n" + _LEG.format(s="Right", x=-9) + _LEG.format(s="Left", x=9) + "}\n"
                    "MOTION\nFrames: 2\nFrame Time: 0.01\n" + ("0 93 0" + " 0" * 27 + "\n") * 2)
    return path


def test_bvh_spec_looked_up_in_the_data_dir(tmp_path, monkeypatch):
    data = tmp_path / "data"
    _bvh(data / "subj" / "xsens" / "walk.bvh")
    monkeypatch.chdir(tmp_path)                                        # relative path not valid from here
    for spec in ("bvh:subj/xsens/walk.bvh", "bvh:xsens/walk.bvh", "bvh:walk.bvh"):
        skel = skeleton_from_spec(spec, LOWER_BODY, data_dir=str(data))
        assert skel.names == tuple(LOWER_BODY)
        thigh = -dict(zip(skel.names, skel.offsets))["LeftLowerLeg"]
        assert np.allclose(np.abs(thigh).max(), 0.45)                   # the file's 45 cm
    monkeypatch.setenv("IMUGRAPH_DATA", str(data))                     # default data dir: $IMUGRAPH_DATA
    assert skeleton_from_spec("bvh:xsens/walk.bvh").names == tuple(LOWER_BODY)
    with pytest.raises(SessionError, match="nope.bvh: field 'file': found no such file.*expected an existing BVH"):
        skeleton_from_spec("bvh:nope.bvh", data_dir=str(data))


def test_mocap_apply_skeleton_passes_data_dir(mini, tmp_path, monkeypatch):
    from imugraph.commands.mocap import apply_skeleton

    data = tmp_path / "data"
    _bvh(data / "xsens" / "walk.bvh")
    monkeypatch.chdir(tmp_path)
    s = apply_skeleton(read_body_session(mini), "bvh:xsens/walk.bvh", str(data))
    assert s.meta["skeleton"] == "--skeleton bvh:xsens/walk.bvh" and s.skeleton.sensed == tuple(LOWER_BODY)
