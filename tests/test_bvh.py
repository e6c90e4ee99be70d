"""BVH reading (forward kinematics against hand-computed poses, real CMU/Xsens files) and writing (round trip)."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.body.bvh_map import segment_motion
from imugraph.body.skeleton import full_body, lower_body
from imugraph.errors import SessionError
from imugraph.geometry import expmap, quat_conj, quat_mul, quat_to_rotvec, rotmat_to_quat
from imugraph.io.bvh import read_bvh, write_bvh

TINY = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Arm
  {
    OFFSET 1 0 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 0 1
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 3 0 0 0 0 0 0
1 2 3 90 0 0 90 90 0
"""


def _angle_deg(q1, q2):
    return np.rad2deg(np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(q1), q2)), axis=-1))


def test_tiny_bvh_forward_kinematics(tmp_path):
    p = tmp_path / "tiny.bvh"
    p.write_text(TINY)
    b = read_bvh(p)
    assert b.names == ("Hips", "Arm") and b.parents == (-1, 0) and b.frame_time == 0.5
    t, q, pos = b.world_poses(units_m=1.0)
    assert np.allclose(t, [0.0, 0.5])
    # frame 0: rest. File (x, y, z) → n (z, x, y): root (1,2,3) → (3,1,2); arm at root + (1,0,0)_file → +(0,1,0)_n
    assert np.allclose(pos[0], [[3, 1, 2], [3, 2, 2]])
    assert np.allclose(q[0], [1, 0, 0, 0])
    # frame 1: root Rz_file(90°) takes the arm offset (1,0,0) to (0,1,0) in the file: arm at (1,3,3)_file = (3,1,3)_n
    assert np.allclose(pos[1], [[3, 1, 2], [3, 1, 3]])
    # file z is n's x: Rz_file(90°) is Rx_n(90°)
    assert np.allclose(q[1, 0], [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0])
    # arm local = Rz(90)·Rx(90) (listed order): world = Rz(90)·Rz(90)·Rx(90); the end site (0,0,1) maps to
    # Rx(90)(0,0,1) = (0,-1,0), Rz(180)(0,-1,0) = (0,1,0) in the file (the other order would give (0,0,1))
    R_file = expmap(np.array([0, 0, np.pi])) @ expmap(np.array([np.pi / 2, 0, 0]))
    C = np.array([[0, 0, 1.0], [1, 0, 0], [0, 1, 0]])
    assert _angle_deg(q[1, 1], rotmat_to_quat(C @ R_file @ C.T)) < 1e-6
    assert np.allclose(R_file @ [0, 0, 1], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize("text, field", [
    (TINY.replace("MOTION", "MOTON"), "MOTION"),
    (TINY.replace("Zrotation Xrotation Yrotation\n    End", "Zrot Xrotation Yrotation\n    End"), "line 9"),
    (TINY.replace("1 2 3 90 0 0 90 90 0", "1 2 3 90 0 0 90 90"), "MOTION"),
    (TINY.replace("Frame Time: 0.5", "Frame Time: 0"), "line 18"),
    (TINY.replace("OFFSET 1 0 0", "OFFSET 1 zero 0"), "line 8"),
])
def test_bad_bvh_names_line_and_field(tmp_path, text, field):
    p = tmp_path / "bad.bvh"
    p.write_text(text)
    with pytest.raises(SessionError) as e:
        read_bvh(p)
    assert e.value.field == field and str(p) in str(e.value)


def test_missing_file_is_session_error(tmp_path):
    with pytest.raises(SessionError):
        read_bvh(tmp_path / "none.bvh")


def _bone_lengths_constant(b, pos, scale):
    """|p_child − p_parent| equals the offset length in every frame (FK keeps the bones rigid)."""
    for j, p in enumerate(b.parents):
        if p >= 0:
            d = np.linalg.norm(pos[:, j] - pos[:, p], axis=1)
            assert np.allclose(d, scale * np.linalg.norm(b.offsets[j]), atol=1e-9)


def test_cmu_bvh_real(data_file):
    b = read_bvh(data_file("cmu_bvh/scaled_131_01.bvh"))
    assert b.n_frames == 995 and len(b.names) == 31 and abs(b.frame_time - 1 / 120) < 1e-5
    assert b.scale_to_m() == 1.0
    t, q, pos = b.world_poses()
    _bone_lengths_constant(b, pos, 1.0)
    hips, head, lhip, rhip = (b.index(n) for n in ("Hips", "Head", "LeftHip", "RightHip"))
    assert 0.8 < np.median(pos[:, hips, 2]) < 1.1                     # pelvis height, z up
    assert np.all(pos[:, head, 2] > pos[:, hips, 2] + 0.2)
    toes = [b.index("LeftToe"), b.index("RightToe")]
    assert -0.05 < pos[:, toes, 2].min() < 0.1                        # feet reach the floor
    walk = pos[-1, hips, :2] - pos[0, hips, :2]                     # start-walk-stop: ≈ 2.6 m
    assert np.linalg.norm(walk) > 1.5
    # the left hip is on the left of the walking direction (y left of x, z up)
    side = pos[:, lhip, :2] - pos[:, rhip, :2]
    assert np.median(walk[0] * side[:, 1] - walk[1] * side[:, 0]) > 0


def test_xsens_bvh_real_mm(data_file):
    b = read_bvh(data_file("gaittoolbox/xsens/S02-Trial-Walk-1.bvh"))
    assert b.n_frames == 2503 and b.scale_to_m() == 0.001
    t, q, pos = b.world_poses()
    _bone_lengths_constant(b, pos, 0.001)
    assert 0.85 < np.median(pos[1:, 0, 2]) < 1.05
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0)


def _random_pose(skel, rng, T=5):
    q = rotmat_to_quat(expmap(rng.normal(0, 0.6, (T, len(skel.names), 3))))
    return np.arange(T) / 50.0, q, rng.normal(0, 1, (T, 3))


@pytest.mark.parametrize("make", [full_body, lower_body])
def test_write_bvh_round_trip(tmp_path, make):
    skel = make(1.8)
    rng = np.random.default_rng(3)
    t, q, root = _random_pose(skel, rng)
    path = write_bvh(tmp_path / "m.bvh", skel, t, q, root)
    skel2, mapping, t2, q2, p2 = segment_motion(path)
    assert skel2.names == skel.names and mapping == {n: n for n in skel.names}
    assert np.allclose(skel2.offsets, skel.offsets, atol=1e-6)
    assert np.allclose(t2, t, atol=1e-9)
    assert _angle_deg(q2, q).max() < 1e-4
    assert np.allclose(p2, skel.forward_kinematics(q, root), atol=1e-5)


def test_write_bvh_round_trip_cmu(tmp_path, data_file):
    skel, _, t, q, p = segment_motion(data_file("cmu_bvh/scaled_131_02.bvh"))
    path = write_bvh(tmp_path / "cmu.bvh", skel, t[:200], q[:200], p[:200, 0], units_m=0.01)
    skel2, _, t2, q2, p2 = segment_motion(path)
    assert read_bvh(path).scale_to_m() == 0.01
    assert _angle_deg(q2, q[:200]).max() < 1e-4
    assert np.allclose(p2, skel.forward_kinematics(q[:200], p[:200, 0]), atol=1e-5)
