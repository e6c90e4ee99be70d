"""Body models (proportions, forward kinematics, subsets, ties, BVH skeletons) and joint angles."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.body.angles import JOINTS, cardan_yxz, joint_angles, write_joint_angles_csv
from imugraph.body.bvh_map import segment_motion
from imugraph.body.skeleton import (FULL_BODY_SENSED, LOWER_BODY, MVN_SEGMENTS, fill_unsensed, from_bvh,
                                    full_body, lower_body)
from imugraph.errors import SessionError
from imugraph.geometry import expmap, quat_conj, quat_mul, quat_to_rotvec, rotmat_to_quat


def _rq(v):
    return rotmat_to_quat(expmap(np.asarray(v, float)))


def test_full_body_structure_and_winter_proportions():
    H = 1.8
    s = full_body(H)
    assert s.names == MVN_SEGMENTS and len(s.sensed) == 17 and set(s.sensed) == set(FULL_BODY_SENSED)
    assert s.names[0] == "Pelvis" and all(0 <= p < i for i, p in enumerate(s.parents) if i)
    pos = s.neutral_positions() + [0, 0, 0.530 * H]            # pelvis origin at hip-joint height
    z = {n: pos[s.index(n)][2] for n in s.names}
    assert z["RightLowerLeg"] == pytest.approx(0.285 * H) and z["LeftFoot"] == pytest.approx(0.039 * H)
    assert z["RightUpperArm"] == pytest.approx(0.818 * H)
    head_top = pos[s.index("Head")] + s.ends[s.index("Head")]
    assert head_top[2] == pytest.approx(H)
    toe_tip = pos[s.index("LeftToe")] + s.ends[s.index("LeftToe")]
    assert abs(toe_tip[2]) < 0.01 * H
    assert np.linalg.norm(pos[s.index("LeftUpperLeg")] - pos[s.index("RightUpperLeg")]) == pytest.approx(0.191 * H)
    assert np.linalg.norm(pos[s.index("LeftUpperArm")] - pos[s.index("RightUpperArm")]) == pytest.approx(0.259 * H)
    assert np.linalg.norm(s.offsets[s.index("RightHand")]) == pytest.approx(0.146 * H)


def test_lower_body_is_subset():
    lb = lower_body(1.7)
    assert lb.names == LOWER_BODY and lb.sensed == LOWER_BODY
    fb = full_body(1.7)
    for n in lb.names:
        assert np.allclose(lb.offsets[lb.index(n)], fb.offsets[fb.index(n)])
    # removing intermediates joins their offsets (all frames coincide in the neutral pose)
    sub = fb.subset(["Pelvis", "T8", "Head"])
    assert sub.parents == (-1, 0, 1)
    assert np.allclose(sub.offsets[1], fb.neutral_positions()[fb.index("T8")])
    assert sub.children("Pelvis") == ["T8"]
    with pytest.raises(SessionError):
        fb.subset(["Pelvis", "Tail"])
    with pytest.raises(SessionError):
        full_body(4.0)


def test_forward_kinematics_known_answer():
    H = 1.75
    s = lower_body(H)
    T = 2
    q = np.tile([1.0, 0, 0, 0], (T, len(s.names), 1))
    root = np.array([[0, 0, 1.0], [1.0, 2.0, 1.0]])
    q[1, :] = _rq([0, 0, np.pi / 2])                              # everything yawed 90°: y → −x
    q[1, s.index("LeftUpperLeg")] = quat_mul(_rq([0, 0, np.pi / 2]), _rq([0, -np.pi / 2, 0]))  # hip flexed 90°
    p = s.forward_kinematics(q, root)
    half_hip, thigh = 0.191 * H / 2, (0.530 - 0.285) * H
    assert np.allclose(p[0, s.index("LeftUpperLeg")], [0, half_hip, 1.0])
    assert np.allclose(p[0, s.index("RightFoot")], [0, -half_hip, 1.0 - (0.530 - 0.039) * H])
    hip = np.array([1.0 - half_hip, 2.0, 1.0])
    assert np.allclose(p[1, s.index("LeftUpperLeg")], hip)
    # thigh horizontal, pointing along the yawed forward axis (+y): knee = hip + thigh·(0, 1, 0)
    assert np.allclose(p[1, s.index("LeftLowerLeg")], hip + [0, thigh, 0])
    with pytest.raises(SessionError):
        s.forward_kinematics(q[:, :3], root)


def test_fill_unsensed_ties():
    s = full_body()
    T = 3
    given = {n: np.tile([1.0, 0, 0, 0], (T, 1)) for n in s.sensed}
    given["T8"] = np.tile(_rq([0, 0, np.deg2rad(40)]), (T, 1))
    given["Head"] = np.tile(_rq([np.deg2rad(30), 0, 0]), (T, 1))
    given["LeftFoot"] = np.tile(_rq([0, 0.3, 0]), (T, 1))
    q = fill_unsensed(s, given)
    assert np.allclose(q[:, s.index("L5")], _rq([0, 0, np.deg2rad(10)]))
    assert np.allclose(q[:, s.index("L3")], _rq([0, 0, np.deg2rad(20)]))
    assert np.allclose(q[:, s.index("T12")], _rq([0, 0, np.deg2rad(30)]))
    # Neck halfway between Rz(40°) and Rx(30°): equal angles to both
    neck = q[:, s.index("Neck")]
    d = [np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(neck), given[k])), axis=1) for k in ("T8", "Head")]
    assert np.allclose(d[0], d[1])
    assert np.allclose(q[:, s.index("LeftToe")], given["LeftFoot"])
    del given["T8"]
    with pytest.raises(SessionError):
        fill_unsensed(s, given)


def test_from_bvh_cmu_and_xsens(data_file):
    cmu, m = from_bvh(data_file("cmu_bvh/scaled_131_01.bvh"))
    assert m["RightUpperLeg"] == "RightHip" and len(cmu.sensed) == 17
    assert set(cmu.names) == set(MVN_SEGMENTS) - {"L3", "T12"}
    xs, m2 = from_bvh(data_file("gaittoolbox/xsens/S02-Trial-Walk-1.bvh"))
    assert xs.names == MVN_SEGMENTS and m2["T8"] == "Chest4"
    for sk in (cmu, xs):     # limbs hang straight down in the neutral pose (T-pose arms, splayed CMU legs undone)
        for n in ("LeftUpperArm", "RightForeArm", "LeftUpperLeg", "RightLowerLeg"):
            e = sk.ends[sk.index(n)]
            assert e[2] < 0 and np.hypot(e[0], e[1]) < 1e-6
    assert np.linalg.norm(xs.ends[xs.index("RightUpperLeg")]) == pytest.approx(0.4849, abs=1e-3)


def test_cardan_known_rotations():
    a, b, c = 0.4, -0.3, 0.7
    R = expmap(np.array([0, a, 0])) @ expmap(np.array([b, 0, 0])) @ expmap(np.array([0, 0, c]))
    assert np.allclose(cardan_yxz(R), [a, b, c])


def _pose(skel, T=1):
    return np.tile([1.0, 0, 0, 0], (T, len(skel.names), 1))


@pytest.mark.parametrize("side", ["Right", "Left"])
def test_joint_angle_signs(side):
    s = full_body()
    q = _pose(s, 6)
    lat = 1.0 if side == "Left" else -1.0
    # 0: hip flexed 30° (thigh forward: knee moves to +x) — rotation about +y by −30°
    q[0, s.index(f"{side}UpperLeg")] = _rq([0, -np.deg2rad(30), 0])
    # 1: knee flexed 50° (shank backward) with the thigh vertical
    q[1, s.index(f"{side}LowerLeg")] = _rq([0, np.deg2rad(50), 0])
    # 2: hip abducted 20° (leg moves away from the midline)
    q[2, s.index(f"{side}UpperLeg")] = _rq([lat * np.deg2rad(20), 0, 0])
    # 3: hip internally rotated 15° (front of the thigh turns to the midline)
    q[3, s.index(f"{side}UpperLeg")] = _rq([0, 0, -lat * np.deg2rad(15)])
    # 4: ankle dorsiflexed 10° (toes up), elbow flexed 90° (forearm forward)
    q[4, s.index(f"{side}Foot")] = _rq([0, -np.deg2rad(10), 0])
    q[4, s.index(f"{side}ForeArm")] = _rq([0, -np.pi / 2, 0])
    # 5: whole body yawed 70° and pitched: no joint angle changes
    q[5] = _rq([0.2, 0.3, 1.2])
    ang = joint_angles(s, q)
    hip, knee, ankle, elbow = (ang[f"{side}{j}"] for j in ("Hip", "Knee", "Ankle", "Elbow"))
    # sanity of the setup: the flexed thigh's knee end is in front of the hip
    knee_dir = expmap(np.array([0, -np.deg2rad(30), 0])) @ s.ends[s.index(f"{side}UpperLeg")]
    assert knee_dir[0] > 0
    assert np.allclose(hip[0], [30, 0, 0], atol=1e-9)
    assert np.allclose(knee[1], [50, 0, 0], atol=1e-9)
    assert np.allclose(hip[2], [0, 20, 0], atol=1e-9)
    assert np.allclose(hip[3], [0, 0, 15], atol=1e-9)
    assert np.allclose(ankle[4], [10, 0, 0], atol=1e-9) and np.allclose(elbow[4], [90, 0, 0], atol=1e-9)
    for a in ang.values():
        assert np.allclose(a[5], 0, atol=1e-9)
    assert set(joint_angles(lower_body(), _pose(lower_body()))) == {
        "RightHip", "RightKnee", "RightAnkle", "LeftHip", "LeftKnee", "LeftAnkle"}


def test_joint_angles_xsens_walk_plausible(data_file):
    skel, _, t, q, _ = segment_motion(data_file("gaittoolbox/xsens/S02-Trial-Walk-1.bvh"))
    ang = joint_angles(skel, q[1:])
    for side in ("Right", "Left"):
        knee = ang[f"{side}Knee"][:, 0]
        assert 45 < knee.max() < 80 and knee.min() > -15           # swing-phase knee flexion of walking
        hip = ang[f"{side}Hip"][:, 0]
        assert 15 < hip.max() < 50 and -35 < hip.min() < 0


def test_write_joint_angles_csv(tmp_path):
    t = np.array([0.0, 0.01])
    ang = {"RightKnee": np.array([[1, 2, 3], [4, 5, 6.5]])}
    p = write_joint_angles_csv(tmp_path / "joint_angles.csv", t, ang)
    lines = p.read_text().splitlines()
    assert lines[0] == "t,RightKnee_flexion,RightKnee_abduction,RightKnee_rotation"
    assert np.allclose(np.loadtxt(p, delimiter=",", skiprows=1), [[0, 1, 2, 3], [0.01, 4, 5, 6.5]])
    assert list(tmp_path.iterdir()) == [p]
    assert set(JOINTS["RightKnee"]) == {"RightUpperLeg", "RightLowerLeg"}
