"""Body scoring (imugraph.body.evaluate): known answers built here from the documented conventions."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.body.evaluate import (VICON_AXES, best_heading, compare_with_vicon, fit_segment_alignment,
                                    joint_angle_rmse, relative_position_error, rz, score_against_truth, wrap_deg)
from imugraph.body.skeleton import lower_body
from imugraph.config import data_dir
from imugraph.errors import SessionError
from imugraph.geometry import expmap, quat_to_rotmat, rotmat_to_quat


def ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def flexion_only_poses(T=400, seed=0):
    """Lower-body rotations (T, 7, 3, 3) whose hips, knees and ankles only flex (rotation about the lateral y)."""
    rng = np.random.default_rng(seed)
    skel = lower_body()
    t = np.arange(T) / 100.0
    R = np.zeros((T, len(skel.names), 3, 3))
    R[:, 0] = expmap(np.stack([0.1 * np.sin(t), 0.05 * np.cos(2 * t), 0.8 * np.sin(0.3 * t)], -1))
    for i, name in enumerate(skel.names[1:], 1):
        ph, amp = rng.uniform(0, 6), rng.uniform(0.2, 0.6)
        R[:, i] = R[:, skel.parents[i]] @ np.stack([ry(a) for a in amp * np.sin(2 * np.pi * 0.9 * t + ph)])
    return skel, t, R


def test_wrap_deg():
    assert np.allclose(wrap_deg([0, 181, -181, 360, 540, -90]), [0, -179, 179, 0, 180, -90])


def test_constant_shank_offset_gives_known_knee_and_ankle_errors():
    skel, _, R = flexion_only_poses()
    d = np.deg2rad(3.0)
    Re = R.copy()
    k = skel.index("RightLowerLeg")
    Re[:, k] = R[:, k] @ ry(d)            # shank turned by +3° about its lateral axis
    r = joint_angle_rmse(skel, rotmat_to_quat(Re), rotmat_to_quat(R))
    # knee = thigh→shank gains Ry(+3°) on the right: knee flexion (+1 · α) off by 3°; ankle = shank→foot gains
    # Ry(−3°) on the left: α − 3°, reported as dorsiflexion (−1 · α), off by 3°; every other column exact
    assert r["RightKnee"]["flexion"] == pytest.approx(3.0, abs=1e-9)
    assert r["RightAnkle"]["flexion"] == pytest.approx(3.0, abs=1e-9)
    assert r["RightKnee"]["all"] == pytest.approx(3.0 / np.sqrt(3), abs=1e-9)
    for j in ("RightHip", "LeftHip", "LeftKnee", "LeftAnkle"):
        assert r[j]["all"] < 1e-9
    for c in ("abduction", "rotation"):
        assert r["RightKnee"][c] < 1e-9 and r["RightAnkle"][c] < 1e-9


def test_mask_selects_samples():
    skel, _, R = flexion_only_poses(T=100)
    Re = R.copy()
    k = skel.index("LeftUpperLeg")
    Re[50:, k] = R[50:, k] @ ry(np.deg2rad(4.0))
    mask = np.arange(100) >= 50
    assert joint_angle_rmse(skel, rotmat_to_quat(Re), rotmat_to_quat(R), mask)["LeftHip"]["flexion"] == \
        pytest.approx(4.0, abs=1e-9)
    assert joint_angle_rmse(skel, rotmat_to_quat(Re), rotmat_to_quat(R), ~mask)["LeftHip"]["all"] < 1e-9
    with pytest.raises(SessionError):
        joint_angle_rmse(skel, rotmat_to_quat(Re), rotmat_to_quat(R), mask[:10])


def test_best_heading_recovers_rotation():
    rng = np.random.default_rng(1)
    b = rng.standard_normal((500, 3))
    psi = np.deg2rad(-127.0)
    a = b @ rz(-psi).T                       # b = Rz(ψ) a
    assert best_heading(a, b) == pytest.approx(psi, abs=1e-12)


def test_relative_position_error_known_answer():
    rng = np.random.default_rng(2)
    T, S = 300, 5
    ref = rng.standard_normal((T, S, 3))
    rel = ref - ref[:, :1]
    rel_err = rel.copy()
    rel_err[:, 3, 2] += 0.02                 # segment 3 is 2 cm too high: vertical, so ψ is unaffected
    psi0 = np.deg2rad(40.0)
    est = rel_err @ rz(-psi0).T + rng.standard_normal((T, 1, 3))     # heading turned, root translated
    names = ["Pelvis", "A", "B", "C", "D"]
    r = relative_position_error(names, est, ref)
    assert r["heading_deg"] == pytest.approx(40.0, abs=1e-9)
    assert r["per_segment"]["C"] == pytest.approx(0.02, abs=1e-12)
    assert all(r["per_segment"][n] < 1e-12 for n in ("A", "B", "D"))
    assert r["rms_m"] == pytest.approx(0.02 / 2, abs=1e-12)           # sqrt(0.02² / 4 segments)
    assert r["max_segment"] == "C"
    assert relative_position_error(names, est, ref, align_heading=False)["rms_m"] > 0.1


def test_score_against_truth_on_exact_result():
    skel, _, R = flexion_only_poses(T=50)
    q = rotmat_to_quat(R)
    pos = skel.forward_kinematics(q, np.zeros((50, 3)))
    res = SimpleNamespace(names=skel.names, n_quat=q, n_pos=pos @ rz(0.3).T)      # heading-turned estimate
    truth = {"names": list(skel.names)[::-1], "n_quat": q[:, ::-1], "n_pos": pos[:, ::-1]}   # other order
    sc = score_against_truth(res, truth, skel)
    assert sc["position"]["rms_m"] < 1e-12 and sc["position"]["heading_deg"] == pytest.approx(-np.rad2deg(0.3))
    assert sc["joint_rmse_max_deg"] < 1e-9
    with pytest.raises(SessionError):
        score_against_truth(res, {"names": ["Pelvis"], "n_quat": q[:, :1], "n_pos": pos[:, :1]}, skel)


def _vicon_from(R_mvn, start=100, n=300):
    """A Vicon-like dict whose feet carry the Vicon axes (x down, z forward): R_vicon = R_mvn · C_footᵀ."""
    skel = lower_body()
    quat = {s: rotmat_to_quat(R_mvn[start:start + n, i] @ VICON_AXES.get(s, np.eye(3)).T)
            for i, s in enumerate(skel.names)}
    return {"imu_index": np.arange(start, start + n), "fs": 100.0, "quat": quat}


def test_vicon_offset_method_recovers_constant_offsets():
    skel, _, R = flexion_only_poses(T=500)
    vic = _vicon_from(R)
    Re = R.copy()
    k = skel.index("LeftLowerLeg")
    Re[:, k] = R[:, k] @ ry(np.deg2rad(5.0))
    Re = np.einsum("ab,tsbc->tsac", rz(1.0), Re)                    # another world heading: no effect on angles
    est = {s: rotmat_to_quat(Re[:, i]) for i, s in enumerate(skel.names)}
    r = compare_with_vicon(vic, est, method="offset", max_shift=3)
    assert r["shift_samples"] == 0 and r["mean_all_deg"] < 1e-6
    assert r["offsets_deg"]["LeftKnee"][0] == pytest.approx(5.0, abs=1e-6)
    assert r["offsets_deg"]["LeftAnkle"][0] == pytest.approx(5.0, abs=1e-6)


def test_vicon_segment_method_removes_alignment_and_finds_shift():
    skel, _, R = flexion_only_poses(T=500, seed=3)
    rng = np.random.default_rng(4)
    # non-flexion motion too, so that a wrong per-segment alignment would show
    R = R @ expmap(0.2 * np.sin(np.arange(500) / 30.0)[:, None, None] * rng.standard_normal((1, 7, 3)))
    vic = _vicon_from(R)
    C = {s: expmap(np.deg2rad(10) * rng.standard_normal(3)) for s in skel.names}
    C["Pelvis"] = ry(np.deg2rad(-8.0)) @ expmap(np.deg2rad([3.0, 0.0, 0.0]))   # pelvis x: no lateral part (W)
    W = rz(2.0)
    shift = 2
    Re = np.stack([W @ R[:, i] @ C[s] for i, s in enumerate(skel.names)], 1)
    Re = np.roll(Re, shift, axis=0)                                 # the estimate lags by 2 samples
    est = {s: rotmat_to_quat(Re[:, i]) for i, s in enumerate(skel.names)}
    r = compare_with_vicon(vic, est, method="segment", max_shift=4)
    assert r["shift_samples"] == shift and r["mean_all_deg"] < 1e-6
    held = compare_with_vicon(vic, est, method="segment", align_s=1.0, max_shift=4)
    assert held["n"] == 200 and held["mean_all_deg"] < 1e-6
    R_e = {s: quat_to_rotmat(est[s][100 + shift:400 + shift]) for s in skel.names}
    R_v = {s: quat_to_rotmat(vic["quat"][s]) @ VICON_AXES.get(s, np.eye(3)) for s in skel.names}
    W_fit, C_fit = fit_segment_alignment(R_e, R_v)
    assert np.allclose(W_fit, W, atol=1e-9)
    assert all(np.allclose(C_fit[s], C[s], atol=1e-9) for s in skel.names)
    with pytest.raises(SessionError):
        compare_with_vicon(vic, est, method="median")


VICON = data_dir() / "gaittoolbox" / "vicon" / "S02-Trial-Walk-1.csv"
MVN_BVH = data_dir() / "gaittoolbox" / "xsens" / "S02-Trial-Walk-1.bvh"


@pytest.mark.skipif(not (VICON.exists() and MVN_BVH.exists()), reason="gaittoolbox data not present")
def test_xsens_mvn_against_vicon_real_data():
    from imugraph.body.bvh_map import segment_motion
    from imugraph.io.gaittoolbox import read_gaittoolbox_vicon

    vic = read_gaittoolbox_vicon(VICON)
    skel, _, _, q, _ = segment_motion(MVN_BVH)
    est = {n: q[:, i] for i, n in enumerate(skel.names)}
    for method in ("offset", "segment"):
        r = compare_with_vicon(vic, est, method=method)
        assert abs(r["shift_samples"]) <= 3
        for j in ("RightHip", "LeftHip", "RightKnee", "LeftKnee"):
            assert 1.0 < r["joints"][j]["flexion"] < 6.0, (method, j, r["joints"][j])
        assert all(1.0 < v["all"] < 15.0 for v in r["joints"].values())


def rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def test_geodesic_column_known_answer_any_axis():
    """Shank turned by θ about an arbitrary fixed axis: knee and ankle joint rotations both differ by exactly θ
    (pRd_knee·Exp(aθ) and Exp(−aθ)·pRd_ankle), whatever the Cardan columns say; the other joints by 0."""
    skel, _, R = flexion_only_poses(T=200, seed=3)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    theta = np.deg2rad(4.0)
    Re = R.copy()
    k = skel.index("RightLowerLeg")
    Re[:, k] = R[:, k] @ expmap(axis * theta)
    r = joint_angle_rmse(skel, rotmat_to_quat(Re), rotmat_to_quat(R))
    assert r["RightKnee"]["geodesic"] == pytest.approx(4.0, abs=1e-6)
    assert r["RightAnkle"]["geodesic"] == pytest.approx(4.0, abs=1e-6)
    for j in ("RightHip", "LeftHip", "LeftKnee", "LeftAnkle"):
        assert r[j]["geodesic"] < 1e-6


def test_geodesic_stays_small_near_cardan_singularity():
    """Hip abducted to 89.5° (β → 90°, the Cardan singularity, as at a raised shoulder) and a 1° error about
    the thigh's own y axis: the geodesic column is 1°, while the Cardan flexion/rotation columns swing by
    tens of degrees (α and γ become interchangeable)."""
    skel = lower_body()
    T = 50
    R = np.tile(np.eye(3), (T, len(skel.names), 1, 1))
    i = skel.index("RightUpperLeg")
    for c in skel.names:                               # the whole right leg follows the thigh
        if c.startswith("Right"):
            R[:, skel.index(c)] = rx(np.deg2rad(-89.5))
    Re = R.copy()
    Re[:, i] = R[:, i] @ expmap(np.array([0.0, np.deg2rad(1.0), 0.0]))
    r = joint_angle_rmse(skel, rotmat_to_quat(Re), rotmat_to_quat(R))
    assert r["RightHip"]["geodesic"] == pytest.approx(1.0, abs=1e-6)
    assert max(r["RightHip"]["flexion"], r["RightHip"]["rotation"]) > 10.0
    assert r["LeftHip"]["geodesic"] < 1e-6


def test_geodesic_offset_removal_and_truth_summary():
    """A constant joint-rotation offset is removed by offsets=True (geodesic 0), kept without it; the
    truth scoring reports the worst geodesic joint."""
    from imugraph.body.evaluate import joint_geodesic_errors
    skel, _, R = flexion_only_poses(T=100, seed=1)
    Re = R.copy()
    k = skel.index("LeftFoot")
    Re[:, k] = R[:, k] @ expmap(np.array([0.02, 0.05, -0.03]))
    g0 = joint_geodesic_errors(skel, rotmat_to_quat(Re), rotmat_to_quat(R))
    g1 = joint_geodesic_errors(skel, rotmat_to_quat(Re), rotmat_to_quat(R), offsets=True)
    assert np.allclose(g0["LeftAnkle"], np.rad2deg(np.linalg.norm([0.02, 0.05, -0.03])), atol=1e-6)
    assert np.max(g1["LeftAnkle"]) < 1e-6
    res = SimpleNamespace(names=skel.names, n_quat=rotmat_to_quat(Re), n_pos=np.zeros((100, len(skel.names), 3)))
    truth = {"names": skel.names, "n_quat": rotmat_to_quat(R), "n_pos": np.zeros((100, len(skel.names), 3))}
    sc = score_against_truth(res, truth, skel)
    assert sc["joint_geodesic_max_deg"] == pytest.approx(g0["LeftAnkle"][0], abs=1e-6)
