"""BVH-driven body simulator: readings against an analytic motion, strapdown integration back to the truth."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.body.skeleton import lower_body
from imugraph.errors import SessionError
from imugraph.geometry import (expmap, integrate_gyro, quat_conj, quat_mul, quat_to_rotmat, quat_to_rotvec,
                               rotmat_to_quat)
from imugraph.sim.body import (BodyMotion, Placement, motion_from_bvh, nominal_placement, random_placements,
                               simulate_body)
from imugraph.sim.sensors import SensorParams

G = 9.81


def _angle_deg(q1, q2):
    return np.rad2deg(np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(q1), q2)), axis=-1))


def _n_acc(session, g=G):
    """Linear acceleration in n recovered from a noise-free accelerometer: nRs·acc + n_grav."""
    return np.einsum("tab,tb->ta", quat_to_rotmat(session.quat), session.acc) - [0, 0, g]


def test_analytic_rigid_motion():
    """All segments turn rigidly about z by ψ(t) = B sin Ωt while the root moves as A sin ωt along x."""
    skel = lower_body()
    A, w, B, W = 0.3, 2 * np.pi * 0.7, 0.8, 2 * np.pi * 0.4
    t = np.arange(0, 6.0, 0.01)
    psi = B * np.sin(W * t)
    q = np.repeat(rotmat_to_quat(expmap(np.outer(psi, [0, 0, 1.0])))[:, None], len(skel.names), 1)
    root = np.column_stack([A * np.sin(w * t), np.zeros_like(t), np.ones_like(t)])
    motion = BodyMotion(t, skel.names, q, skel.forward_kinematics(q, root))
    name = "LeftLowerLeg"
    pl = Placement(bRs=expmap(np.array([0.3, -0.2, 0.5])), b_pos=np.array([0.06, 0.02, -0.2]))
    rng = np.random.default_rng(0)
    bs = simulate_body(motion, skel, {name: pl}, SensorParams(), rng)
    s = bs.sensors[name]
    # analytic: r = sensor position relative to the root in the un-yawed pose (constant)
    r = skel.neutral_positions()[skel.index(name)] + pl.b_pos

    def vel(tt):
        ps, dps = B * np.sin(W * tt), B * W * np.cos(W * tt)
        c, sn = np.cos(ps), np.sin(ps)
        dR_r = np.column_stack([-sn * r[0] - c * r[1], c * r[0] - sn * r[1], 0 * tt]) * dps[:, None]
        return np.column_stack([A * w * np.cos(w * tt), 0 * tt, 0 * tt]) + dR_r

    a_true = (vel(t[1:]) - vel(t[:-1])) / 0.01                     # interval-mean acceleration (P3)
    err = np.abs(_n_acc(s)[:-1] - a_true)
    assert err[5:-5].max() < 2e-3 * np.abs(a_true).max()           # spline error only (ends excluded)
    # the gyro: turn about n's z by Δψ over each interval, in sensor axes
    s_w = np.einsum("ba,tb->ta", pl.bRs, np.outer(np.diff(psi) / 0.01, [0, 0, 1.0]))
    assert np.allclose(s.gyr[:-1], s_w, atol=1e-9)
    assert np.allclose(bs.truth["sensor_pos"][name], root + np.einsum(
        "tab,b->ta", quat_to_rotmat(q[:, 0]), r), atol=1e-9)


@pytest.fixture(scope="module")
def cmu(data_dir):
    path = data_dir / "cmu_bvh" / "scaled_131_01.bvh"
    if not path.exists():
        pytest.skip("cmu_bvh absent")
    skel, motion = motion_from_bvh(path, rate_hz=60.0, npose_s=2.0, blend_s=1.0)
    rng = np.random.default_rng(7)
    bs = simulate_body(motion, skel, random_placements(skel, rng), SensorParams(), rng)
    return skel, motion, bs


def test_motion_from_bvh_npose_prefix(cmu):
    skel, motion, bs = cmu
    assert motion.t[1] == pytest.approx(1 / 60) and motion.t[-1] > 10.0
    assert motion.names == skel.names and motion.n_quat.shape == (motion.t.size, len(skel.names), 4)
    pre = motion.t < 2.0
    q = motion.n_quat[pre]
    # static N-pose: every segment has the same rotation, a pure heading about z, constant
    R = quat_to_rotmat(q)
    assert np.allclose(R, R[:1, :1], atol=1e-9)
    assert np.allclose(R[0, 0][2], [0, 0, 1], atol=1e-9)
    assert np.allclose(motion.n_pos[pre], motion.n_pos[:1], atol=1e-9)
    for s in bs.sensors.values():
        assert np.allclose(s.gyr[pre][:-1], 0, atol=1e-6)   # the splines leak ~1e-9 before the blend
        assert np.allclose(np.linalg.norm(s.acc[pre][:-2], axis=1), G, atol=1e-6)
    # positions are the skeleton's forward kinematics (joint constraints hold exactly)
    assert np.allclose(motion.n_pos, skel.forward_kinematics(motion.n_quat, motion.n_pos[:, 0]))


def test_gyro_integrates_to_truth(cmu):
    _, motion, bs = cmu
    k = np.flatnonzero(motion.t <= motion.t[0] + 10.0)
    for name, s in bs.sensors.items():
        q = integrate_gyro(s.gyr[k], s.dt[k], s.quat[k[0]])
        assert _angle_deg(q, s.quat[k]).max() < 0.5, name


def test_accelerometer_double_integrates_to_position(cmu):
    _, motion, bs = cmu
    dt = 1 / 60
    for name, s in bs.sensors.items():
        a = _n_acc(s)
        P, V = bs.truth["sensor_pos"][name], bs.truth["sensor_vel"][name]
        worst = 0.0
        for k0 in range(0, motion.t.size - 61, 20):                # every 1 s window
            p, v = P[k0].copy(), V[k0].copy()
            for k in range(k0, k0 + 60):
                p, v = p + v * dt + 0.5 * a[k] * dt**2, v + a[k] * dt
            worst = max(worst, np.linalg.norm(p - P[k0 + 60]))
        assert worst < 5e-3, (name, worst)


def test_random_placements_plausible():
    skel = lower_body()
    p1 = random_placements(skel, np.random.default_rng(1), max_angle_deg=20)
    p2 = random_placements(skel, np.random.default_rng(1), max_angle_deg=20)
    assert set(p1) == set(skel.sensed)
    for name, pl in p1.items():
        assert np.allclose(pl.bRs, p2[name].bRs) and np.allclose(pl.b_pos, p2[name].b_pos)
        assert np.allclose(pl.bRs.T @ pl.bRs, np.eye(3)) and np.linalg.det(pl.bRs) == pytest.approx(1)
        nom = nominal_placement(skel, name)
        ang = np.rad2deg(np.linalg.norm(quat_to_rotvec(rotmat_to_quat(nom.bRs.T @ pl.bRs))))
        assert ang <= 20 + 1e-9
        assert np.linalg.norm(pl.b_pos - nom.b_pos) <= 0.03 * np.sqrt(2) + 1e-12
        assert 0.0 < np.linalg.norm(pl.b_pos) < 0.5
    # thigh sensors sit on the outer side, at mid-thigh
    assert nominal_placement(skel, "RightUpperLeg").b_pos[1] < 0 < nominal_placement(skel, "LeftUpperLeg").b_pos[1]


def test_simulate_body_per_sensor_params_and_errors():
    skel = lower_body()
    t = np.arange(0, 1, 0.01)
    q = np.tile([1.0, 0, 0, 0], (t.size, len(skel.names), 1))
    motion = BodyMotion(t, skel.names, q, skel.forward_kinematics(q, np.zeros((t.size, 3))))
    pls = {n: nominal_placement(skel, n) for n in ("Pelvis", "LeftFoot")}
    params = {"Pelvis": SensorParams(gyro_bias=[0.1, 0, 0]), "LeftFoot": SensorParams(acc_noise=0.5)}
    bs = simulate_body(motion, skel, pls, params, np.random.default_rng(0))
    assert np.allclose(bs.sensors["Pelvis"].gyr[:, 0], 0.1)
    assert 0.3 < np.std(bs.sensors["LeftFoot"].acc[:, 0]) < 0.7
    with pytest.raises(SessionError):
        simulate_body(motion, skel, pls, {"Pelvis": SensorParams()}, np.random.default_rng(0))
    with pytest.raises(SessionError):
        simulate_body(BodyMotion(t, skel.names[:3], q[:, :3], motion.n_pos[:, :3]), skel, pls, SensorParams(),
                      np.random.default_rng(0))


def test_xsens_bvh_reference_frame_dropped(data_file):
    from imugraph.io.bvh import read_bvh
    path = data_file("gaittoolbox/xsens/S02-Trial-Walk-1.bvh")
    skel, motion = motion_from_bvh(path, rate_hz=50.0, npose_s=1.0, blend_s=0.5, duration_s=2.0)
    assert skel.names[0] == "Pelvis" and len(skel.names) == 23
    _, _, pos = read_bvh(path).world_poses()
    k = np.argmin(np.abs(motion.t - 1.5))                          # first BVH frame used = frame 1, not the T-pose
    assert np.allclose(motion.n_pos[k, 0], pos[1, 0], atol=2e-3)
    assert motion.t[-1] == pytest.approx(3.5, abs=0.03)
