"""Mocap glitch repair (imugraph.body.repair), exact-rotation preintegration, adaptive keyframes, tie rules,
default placements and a 21-segment (CMU-like) skeleton through the estimator."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from imugraph.body.placement import nominal_placement
from imugraph.body.repair import MAX_JOINT_RATE, joint_rates, joint_rotations, repair_glitches
from imugraph.body.skeleton import TIES, fill_unsensed, full_body, lower_body, tie_rules
from imugraph.errors import SessionError
from imugraph.factors.body import exact_rotation_gyro, imu_params, preintegrate
from imugraph.geometry import expmap, logmap, quat_conj, quat_mul, quat_slerp, quat_to_rotvec, rotmat_to_quat
from imugraph.graphs.body_model import BodyOptions, keyframes, sensor_setup

RATE = 120.0


def _chain_motion(F: int = 240):
    """Three segments in a chain (root, child, grandchild): each joint turns at a constant 2 rad/s about its own
    fixed axis (a known geodesic: the slerp of two frames is the analytic rotation in between)."""
    t = np.arange(F) / RATE
    parents = (-1, 0, 1)
    axes = np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]])
    r = np.stack([rotmat_to_quat(expmap(np.outer(2.0 * t, a))) for a in axes], 1)       # joint rotations
    q = r.copy()
    for i in (1, 2):
        q[:, i] = quat_mul(q[:, i - 1], r[:, i])
    return t, parents, r, q


def _angle_deg(a, b):
    return np.rad2deg(np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(a), b)), axis=-1))


def test_single_frame_spike_is_replaced_by_the_geodesic():
    t, parents, r, q = _chain_motion()
    bad = r.copy()
    bad[100, 1] = quat_mul(bad[100, 1], rotmat_to_quat(expmap(np.deg2rad([60.0, 0, 0]))))      # 60° in one frame
    q_bad = q.copy()
    q_bad[:, 1] = quat_mul(q_bad[:, 0], bad[:, 1])
    q_bad[:, 2] = quat_mul(q_bad[:, 1], bad[:, 2])
    fixed, rep = repair_glitches(parents, ("A", "B", "C"), t, q_bad)
    assert rep["frames"] == {"B": 1} and rep["frames_total"] == 1 and not rep["unrepaired_runs"]
    assert rep["max_rate_before"]["B"] > 100 and rep["max_rate_after"]["B"] <= MAX_JOINT_RATE
    assert _angle_deg(fixed, q).max() < 1e-6          # joint B back on its analytic path, C follows it, A untouched
    # joint C's own rotation is unchanged everywhere (only its parent was repaired)
    assert _angle_deg(joint_rotations(parents, fixed)[:, 2], r[:, 2]).max() < 1e-6


def test_step_is_spread_below_the_limit_and_clean_motion_untouched():
    t, parents, r, q = _chain_motion()
    step = r.copy()
    step[120:, 2] = quat_mul(step[120:, 2], rotmat_to_quat(expmap(np.deg2rad([0, 0, 90.0]))))  # stays turned
    q_step = q.copy()
    q_step[:, 2] = quat_mul(q_step[:, 1], step[:, 2])
    fixed, rep = repair_glitches(parents, ("A", "B", "C"), t, q_step)
    w = joint_rates(t, joint_rotations(parents, fixed))
    assert w.max() <= MAX_JOINT_RATE * (1 + 1e-6) and rep["frames"]["C"] >= 4
    assert _angle_deg(fixed[:100], q_step[:100]).max() < 1e-9 and _angle_deg(fixed[140:], q_step[140:]).max() < 1e-9
    clean, rep0 = repair_glitches(parents, ("A", "B", "C"), t, q)
    assert rep0["frames"] == {} and _angle_deg(clean, q).max() < 1e-9
    with pytest.raises(SessionError):
        repair_glitches(parents, ("A", "B", "C"), t[:-1], q)


def test_motion_from_bvh_repairs_before_filtering(tmp_path):
    """A BVH written with one glitched frame: motion_from_bvh reports and removes it (low-pass off)."""
    from imugraph.io.bvh import write_bvh
    from imugraph.sim.body import motion_from_bvh

    skel = lower_body()
    F = 200
    t = np.arange(F) / RATE
    knee = skel.index("RightLowerLeg")
    r = np.tile([1.0, 0, 0, 0], (F, len(skel.names), 1))
    r[:, knee] = rotmat_to_quat(expmap(np.outer(0.5 * np.sin(2 * np.pi * t), [0, 1.0, 0])))        # knee flexes
    clean = r.copy()
    for i in range(1, len(skel.names)):                       # world rotations (lower body: parents first)
        clean[:, i] = quat_mul(clean[:, skel.parents[i]], r[:, i])
    glitch = clean.copy()
    turn = rotmat_to_quat(expmap(np.deg2rad([0, 0, 70.0])))
    for i in (knee, skel.index("RightFoot")):                 # the shank and its foot jump for one frame
        glitch[90, i] = quat_mul(glitch[90, i], turn) if i == knee else quat_mul(glitch[90, knee], r[90, i])
    root = np.column_stack([0.3 * t, np.zeros(F), np.full(F, 0.9)])
    path = write_bvh(tmp_path / "glitch.bvh", skel, t, glitch, root)
    kw = dict(rate_hz=RATE, npose_s=0.0, blend_s=0.0, lowpass_hz=None, skip_s=0.0)
    _, mot = motion_from_bvh(path, **kw)
    assert mot.info["repair"]["frames"] == {"RightLowerLeg": 1}
    k = int(np.argmin(np.abs(mot.t - t[90])))
    assert _angle_deg(mot.n_quat[k, knee], clean[90, knee]) < 0.1
    _, raw = motion_from_bvh(path, max_joint_rate=None, **kw)
    assert raw.info["repair"] == {} and _angle_deg(raw.n_quat[k, knee], clean[90, knee]) > 60


def test_exact_rotation_gyro_reproduces_the_rotation_product():
    rng = np.random.default_rng(3)
    N, dt = 49, np.full(49, 1 / 60)
    w = rng.standard_normal((N, 3))
    w *= 20.0 / np.linalg.norm(w, axis=1)[:, None]              # 20 rad/s, axis changing every sample
    acc = rng.standard_normal((N, 3)) * 5
    b = np.array([0.01, -0.02, 0.005])
    kf = keyframes(N, 6)
    prm = imu_params(9.81, np.full(3, 0.003), np.full(3, 0.02), 1 / 60)
    for exact, tol in ((True, 1e-9), (False, None)):
        pims = preintegrate(w, acc, dt, kf, prm, gtsam.imuBias.ConstantBias(np.zeros(3), b), exact)
        err = []
        for j, pim in enumerate(pims):
            R, v = np.eye(3), np.zeros(3)
            for i in range(kf[j], kf[j + 1]):
                v, R = v + R @ acc[i] * dt[i], R @ expmap((w[i] - b) * dt[i])        # exact discrete model
            err.append(max(np.linalg.norm(logmap(R.T @ pim.deltaRij().matrix())), np.linalg.norm(pim.deltaVij() - v)))
        assert (max(err) < tol) if exact else (max(err) > 1e-3)
    assert np.allclose(exact_rotation_gyro(w, dt, kf, b)[kf[-1]:], w[kf[-1]:])


def test_keyframes_split_fast_turns():
    turn = np.full(100, 0.1)
    turn[40:46] = 1.0                                             # 6 rad within one regular interval
    kf = keyframes(100, 6, turn, 2.5)
    assert kf[0] == 0 and kf[-1] == 99 and np.all(np.diff(kf) <= 6)
    sums = [turn[a:b].sum() for a, b in zip(kf[:-1], kf[1:])]
    assert max(sums) <= 2.5 + 1e-12 and kf.size > keyframes(100, 6).size
    assert np.array_equal(keyframes(100, 6, np.full(100, 0.1), 2.5), keyframes(100, 6))


def test_tie_rules_mvn_cmu_and_missing_segments():
    body = full_body()
    assert tie_rules(body, body.sensed) == TIES
    cmu = body.subset([n for n in body.names if n not in ("L3", "T12")])          # the CMU BVH's 21 segments
    assert len(cmu.names) == 21 and tie_rules(cmu, cmu.sensed)["L5"] == ("Pelvis", "T8", 0.5)
    T = 2
    given = {n: np.tile([1.0, 0, 0, 0], (T, 1)) for n in cmu.sensed}
    given["T8"] = np.tile(rotmat_to_quat(expmap(np.array([0, 0, 0.8]))), (T, 1))
    q = fill_unsensed(cmu, given)
    assert np.allclose(q[:, cmu.index("L5")], quat_slerp(given["Pelvis"], given["T8"], np.full(T, 0.5)))
    del given["T8"]                                                # Head and both shoulders hang below it
    with pytest.raises(SessionError, match="L5"):                # the first segment without a rule
        fill_unsensed(cmu, given)
    q2 = fill_unsensed(cmu, given, strict=False)                  # the estimator's output: nearest ancestor
    assert np.allclose(q2[:, cmu.index("T8")], given["Pelvis"])
    with pytest.raises(SessionError, match="Pelvis"):
        fill_unsensed(cmu, {"T8": given["Head"]})


def test_estimator_on_21_segment_skeleton():
    """17 IMUs on a CMU-like skeleton (no L3, T12): the batch estimator runs and ties L5 halfway."""
    from imugraph.graphs.body import solve_body_batch
    from imugraph.sim.body import BodyMotion, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    body = full_body()
    skel = body.subset([n for n in body.names if n not in ("L3", "T12")])
    t = np.arange(0, 4.0, 1 / 60)
    S = len(skel.names)
    env = np.clip((t - 1.5) / 0.5, 0, 1)
    q = np.tile([1.0, 0, 0, 0], (t.size, S, 1))
    for i, name in enumerate(skel.names):
        if name != "Pelvis":
            a = np.array([np.sin(i), np.cos(i), 0.3])
            theta = 0.4 * env * np.sin(2 * np.pi * 0.8 * t + i)
            q[:, i] = rotmat_to_quat(expmap(np.outer(theta, a / np.linalg.norm(a))))
    for i in range(1, S):
        q[:, i] = quat_mul(q[:, skel.parents[i]], q[:, i])
    root = np.column_stack([0.2 * env * np.sin(2 * np.pi * 0.5 * t), np.zeros_like(t), np.full(t.size, 1.0)])
    mot = BodyMotion(t, skel.names, q, skel.forward_kinematics(q, root))
    rng = np.random.default_rng(1)
    sess = simulate_body(mot, skel, random_placements(skel, rng, 10.0), SensorParams(), rng)
    setup = sensor_setup(sess, skel, BodyOptions(), np.arange(60))
    for n in skel.sensed:                                          # the default nominal placement
        assert np.allclose(setup[n].bRs_nom, nominal_placement(skel, n).bRs)
    res = solve_body_batch(sess, BodyOptions(max_iterations=5))
    assert res.names == skel.names and np.all(np.isfinite(res.n_quat))
    i5 = skel.index("L5")
    half = quat_slerp(res.n_quat[:, 0], res.n_quat[:, skel.index("T8")], np.full(t.size, 0.5))
    assert _angle_deg(res.n_quat[:, i5], half).max() < 1e-6


def test_quat_angle_is_the_rotation_angle_for_either_sign():
    from imugraph.geometry import quat_angle, rotvec_to_quat
    rng = np.random.default_rng(3)
    a = rotvec_to_quat(rng.normal(size=3))
    w = np.array([0.0, 0.7, -0.2])                       # a known relative rotation of |w| = 0.728 rad
    b = quat_mul(a, rotvec_to_quat(w))
    assert quat_angle(a, b) == pytest.approx(np.linalg.norm(w), abs=1e-9)
    assert quat_angle(a, -b) == pytest.approx(np.linalg.norm(w), abs=1e-9)
    assert quat_angle(np.stack([a, a]), np.stack([a, b])) == pytest.approx([0.0, np.linalg.norm(w)], abs=1e-6)
