"""Body estimator end to end (imugraph.graphs.body, body_incremental) on synthetic multi-IMU sessions whose
truth is computed independently (tests/body_synth.py; imugraph.sim.body for the BVH-driven case)."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from imugraph.body.placement import nominal_placement
from imugraph.errors import SessionError
from imugraph.geometry import expmap, quat_conj, quat_mul, quat_to_rotvec, rotmat_to_quat
from imugraph.graphs.body import solve_body_batch
from imugraph.graphs.body_incremental import solve_body_incremental
from imugraph.graphs.body_model import BodyOptions, body_joints

sys.path.insert(0, str(Path(__file__).parent))
from body_synth import chain_session, chain_skeleton  # noqa: E402


def pair_error(sess, res, parent: str, child: str) -> float:
    """RMS angle (deg) of the error in the parent→child relative rotation (truth vs estimate)."""
    tq, skel = sess.truth["n_quat"], sess.skeleton
    p, i = skel.index(parent), skel.index(child)
    rt = quat_mul(quat_conj(tq[:, p]), tq[:, i])
    re = quat_mul(quat_conj(res.n_quat[:, p]), res.n_quat[:, i])
    e = np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(rt), re)), axis=1)
    return float(np.rad2deg(np.sqrt(np.mean(e**2))))


def joint_errors(sess, res) -> dict:
    """pair_error for every parent→child joint of the skeleton, keyed by the child."""
    skel = sess.skeleton
    return {skel.names[i]: pair_error(sess, res, skel.names[p], skel.names[i])
            for i, p in enumerate(skel.parents) if p >= 0}


def relpos_error_cm(sess, res) -> float:
    """Max over segments of the RMS error of the origin relative to the root origin, cm (world frame)."""
    tp = sess.truth["n_pos"]
    d = (tp - tp[:, :1]) - (res.n_pos - res.n_pos[:, :1])
    return float(100 * np.max(np.sqrt(np.mean(np.sum(d**2, axis=2), axis=0))))


def rot_err_deg(A, B) -> float:
    return float(np.rad2deg(np.linalg.norm(quat_to_rotvec(rotmat_to_quat(A.T @ B)))))


@pytest.fixture(scope="module")
def chain():
    return chain_session(duration_s=10.0, seed=1)


@pytest.fixture(scope="module")
def chain_result(chain):
    return solve_body_batch(chain, BodyOptions())


def test_joints_between_sensed_segments_lump_unsensed_links():
    joints = body_joints(chain_skeleton(with_spine=True))
    by_child = {j.child: j for j in joints}
    assert set(by_child) == {"RightUpperLeg", "RightLowerLeg", "LeftUpperLeg", "T8"}
    assert by_child["T8"].parent == "Pelvis" and by_child["T8"].lumped
    np.testing.assert_allclose(by_child["T8"].b_parent, [0, 0, 0.35])        # L5 offset + T8 offset
    assert not by_child["RightLowerLeg"].lumped


def test_batch_recovers_chain_from_nominal_placement(chain, chain_result):
    """Unknown placements (up to 30° off the default nominal site): joint rotations, positions and placements
    recovered."""
    res = chain_result
    S = len(chain.skeleton.names)
    assert res.names == chain.skeleton.names
    assert res.n_quat.shape == (chain.t.size, S, 4) and res.n_pos.shape == (chain.t.size, S, 3)
    errs = joint_errors(chain, res)
    assert max(errs.values()) < 1.0, errs
    assert relpos_error_cm(chain, res) < 1.0
    for name, pl in chain.truth["placements"].items():
        assert rot_err_deg(pl["bRs"], res.placements[name]["bRs"]) < 2.0
        assert np.linalg.norm(pl["b_pos"] - res.placements[name]["b_pos"]) < 0.02


def test_relative_heading_observable_only_with_motion():
    """Non-root sensors start 25° off in heading with no heading prior: motion makes the relative headings
    (hence bRs) observable through the joints; a static session cannot (bRs keeps the start error). (Root
    translation alone is enough motion: the joint's acceleration seen by both sensors fixes their relative
    heading, so the static case holds the root still too.)"""
    skel = chain_skeleton()
    wrong = {n: (expmap(np.array([0, 0, np.deg2rad(25.0)])) @ nominal_placement(skel, n).bRs,
                 nominal_placement(skel, n).b_pos) for n in skel.names[1:]}
    opts = BodyOptions(placements=wrong, heading_sigma_rad=None)
    moving = chain_session(duration_s=8.0, seed=2, max_place_deg=5.0)
    res = solve_body_batch(moving, opts)
    assert max(joint_errors(moving, res).values()) < 1.5
    worst = max(rot_err_deg(moving.truth["placements"][n]["bRs"], res.placements[n]["bRs"]) for n in wrong)
    assert worst < 2.0
    static = chain_session(duration_s=6.0, seed=2, max_place_deg=5.0, amp_deg=0.0, root_move=False)
    res_s = solve_body_batch(static, replace(opts, npose=(0.0, 1.0)))
    worst_s = max(rot_err_deg(static.truth["placements"][n]["bRs"], res_s.placements[n]["bRs"]) for n in wrong)
    assert worst_s > 15.0


def test_lumped_spine_joint():
    sess = chain_session(duration_s=8.0, seed=3, with_spine=True)
    res = solve_body_batch(sess, BodyOptions())
    # the truth bends L5 freely; the estimate ties it (slerp): score the sensed pair Pelvis → T8
    assert pair_error(sess, res, "Pelvis", "T8") < 1.5
    assert joint_errors(sess, res)["RightLowerLeg"] < 1.5


def test_hinge_option_keeps_knee_on_its_axis():
    sess = chain_session(duration_s=8.0, seed=4, hinge_knee=True)
    res = solve_body_batch(sess, BodyOptions(hinges=("RightLowerLeg",)))
    assert len(res.info["passes"]) == 2
    i, p = sess.skeleton.index("RightLowerLeg"), sess.skeleton.index("RightUpperLeg")
    rel = quat_to_rotvec(quat_mul(quat_conj(res.n_quat[:, p]), res.n_quat[:, i]))
    off_axis = np.rad2deg(np.sqrt(np.mean(rel[:, 0] ** 2 + rel[:, 2] ** 2)))
    assert off_axis < 1.0
    assert joint_errors(sess, res)["RightLowerLeg"] < 1.0


def test_magnetometer_option():
    sess = chain_session(duration_s=8.0, seed=5, mag=True)
    res = solve_body_batch(sess, BodyOptions(use_mag=True))
    assert max(joint_errors(sess, res).values()) < 1.0


def test_magnetometer_noise_per_sensor_from_first_pass():
    """(B5') one sensor's magnetometer carries a sensor-fixed offset (hard iron: its field direction turns in
    the navigation frame as the segment moves). The first, magnetometer-free pass must give that sensor a large σ
    and the undistorted ones the floor, and the joints must stay as accurate as without the distortion."""
    sess = chain_session(duration_s=8.0, seed=5, mag=True)
    bad = "LeftLowerLeg" if "LeftLowerLeg" in sess.sensors else sorted(sess.sensors)[-1]
    sensors = dict(sess.sensors)
    sensors[bad] = replace(sensors[bad], mag=sensors[bad].mag + np.array([0.6, -0.4, 0.3]))
    distorted = replace(sess, sensors=sensors)
    res = solve_body_batch(distorted, BodyOptions(use_mag=True))
    sig = res.info["mag_sigmas"]
    assert sig[bad] > 1.8 * BodyOptions().mag_sigma
    assert all(v < 1.6 * BodyOptions().mag_sigma for k, v in sig.items() if k != bad)
    assert max(joint_errors(sess, res).values()) < 1.5


def test_bad_input_raises_session_error(chain):
    missing = replace(chain, sensors={k: v for k, v in chain.sensors.items() if k != "LeftUpperLeg"})
    with pytest.raises(SessionError, match="LeftUpperLeg"):
        solve_body_batch(missing)
    short = dict(chain.sensors)
    short["Pelvis"] = short["Pelvis"].slice(0, 100)
    with pytest.raises(SessionError, match="sensors\\[Pelvis\\].t"):
        solve_body_batch(replace(chain, sensors=short))
    with pytest.raises(SessionError, match="skeleton"):
        solve_body_batch(replace(chain, skeleton=None))


def test_incremental_isam2_and_fixed_lag():
    """iSAM2 ends close to the batch solution; the fixed-lag smoother (batch LM on a 1 s window) stays
    within a few degrees once the motion has made the relative headings observable (second half)."""
    sess = chain_session(duration_s=8.0, seed=6)
    batch = solve_body_batch(sess)
    isam = solve_body_incremental(sess, lag_s=None, update_every=5, bootstrap_s=None)
    K = batch.info["keyframes"]
    assert len(isam.info["update_s"]) == int(np.ceil(K / 5))
    assert max(joint_errors(sess, isam).values()) < 1.5
    assert max(joint_errors(sess, batch).values()) < 1.0
    assert max(joint_errors(sess, isam.info["filtered"]).values()) < 3.0
    lag = solve_body_incremental(sess, lag_s=1.0, smoother="batch", update_every=5, bootstrap_s=None)
    assert lag.info["failed_updates"] == 0 and lag.n_quat.shape == batch.n_quat.shape
    h = sess.t.size // 2
    late = replace(sess, truth={**sess.truth, "n_quat": sess.truth["n_quat"][h:]})
    for res in (lag, lag.info["filtered"]):
        tail = replace(batch, n_quat=res.n_quat[h:])
        assert max(joint_errors(late, tail).values()) < 4.0
    with pytest.raises(SessionError, match="lag_s"):
        solve_body_incremental(sess, lag_s=0.2, update_every=5)


def test_fixed_lag_after_batch_bootstrap():
    """Bootstrap (N-pose + motion) in batch, then the fixed lag: close to the batch, bRs held from it."""
    sess = chain_session(duration_s=10.0, seed=9)
    batch = solve_body_batch(sess)
    res = solve_body_incremental(sess, lag_s=1.0, bootstrap_s=5.0)
    boot = res.info["bootstrap"]
    assert boot["keyframes"] == 51 and len(res.info["update_s"]) == int(np.ceil((batch.info["keyframes"] - 51) / 5))
    e_lag, e_b = joint_errors(sess, res), joint_errors(sess, batch)
    assert max(e_b.values()) < 1.0 and max(e_lag.values()) < 2.0
    assert max(joint_errors(sess, res.info["filtered"]).values()) < 2.5


def test_fixed_lag_with_magnetometers_carries_bootstrap_field_model():
    """With magnetometers the stream uses the bootstrap's per-sensor field directions and σ (B5'); a distorted
    sensor stays down-weighted in the stream too (before: no field direction after a bootstrap, a crash)."""
    sess = chain_session(duration_s=10.0, seed=9, mag=True)
    bad = sorted(sess.sensors)[-1]
    sensors = dict(sess.sensors)
    sensors[bad] = replace(sensors[bad], mag=sensors[bad].mag + np.array([0.6, -0.4, 0.3]))
    res = solve_body_incremental(replace(sess, sensors=sensors), BodyOptions(use_mag=True), lag_s=1.0,
                                 bootstrap_s=5.0)
    assert res.info["failed_updates"] == 0
    assert res.info["mag_sigmas"][bad] > 1.8 * BodyOptions().mag_sigma      # the distorted sensor down-weighted
    assert max(joint_errors(sess, res).values()) < 2.0


def test_automatic_bootstrap_waits_for_motion():
    """Default bootstrap "auto": ends once every sensor has turned and accelerated (A1), after the N-pose
    and the motion's start; then Cholesky, close to the batch."""
    sess = chain_session(duration_s=10.0, seed=9)
    batch = solve_body_batch(sess)
    res = solve_body_incremental(sess, lag_s=1.0)
    boot = res.info["bootstrap"]
    assert boot["auto"] and boot["motion_reached"]
    assert 2.5 < boot["bootstrap_s"] < 6.0               # N-pose 2 s, motion blended in over 1 s
    assert res.info["failed_updates"] == 0
    assert max(joint_errors(sess, res).values()) < max(joint_errors(sess, batch).values()) + 1.0
    static = chain_session(duration_s=6.0, seed=2, amp_deg=0.0, root_move=False)
    from imugraph.graphs.body import build_problem
    from imugraph.graphs.body_bootstrap import motion_bootstrap_s
    pb = build_problem(static, BodyOptions(npose=(0.0, 1.0)))
    length, info = motion_bootstrap_s(static, pb, max_s=5.0)
    assert length == 5.0 and not info["motion_reached"]


def _data(rel: str) -> Path:
    from imugraph.config import data_dir
    return Path(data_dir()) / rel


@pytest.mark.skipif(not _data("cmu_bvh/scaled_131_01.bvh").exists(), reason="CMU BVH data absent")
def test_lower_body_from_bvh_simulator():
    """7 sensors on the CMU walk (imugraph.sim.body), unknown placements, nominal placements given."""
    from imugraph.body.skeleton import lower_body
    from imugraph.sim.body import BodyMotion, motion_from_bvh, nominal_placement, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams
    skel, mot = motion_from_bvh(_data("cmu_bvh/scaled_131_01.bvh"), 60.0, duration_s=4.0)
    sub = lower_body().names
    idx = [skel.index(n) for n in sub]
    skel = skel.subset(sub)
    mot = BodyMotion(t=mot.t, names=skel.names, n_quat=mot.n_quat[:, idx], n_pos=mot.n_pos[:, idx])
    rng = np.random.default_rng(0)
    prm = SensorParams(gyro_noise=0.005, acc_noise=0.05)
    sess = simulate_body(mot, skel, random_placements(skel, rng, 30.0), prm, rng)
    nom = {n: (nominal_placement(skel, n).bRs, nominal_placement(skel, n).b_pos) for n in skel.sensed}
    R0 = mot.n_quat[0, 0]
    psi0 = np.rad2deg(np.arctan2(2 * (R0[0] * R0[3] + R0[1] * R0[2]), 1 - 2 * (R0[2] ** 2 + R0[3] ** 2)))
    res = solve_body_batch(sess, BodyOptions(placements=nom, npose_heading_deg=psi0))
    errs = joint_errors(sess, res)
    assert max(errs.values()) < 2.0, errs
    assert relpos_error_cm(sess, res) < 2.0


def test_use_mag_without_magnetometer_raises(chain):
    with pytest.raises(SessionError, match="mag"):
        solve_body_batch(chain, BodyOptions(use_mag=True))


def test_ablation_options_run_and_model_helps():
    """Ablations for issue 4c: no joints (independent sensors), no sensor-to-segment position prior."""
    sess = chain_session(duration_s=8.0, seed=8)
    full = max(joint_errors(sess, solve_body_batch(sess, BodyOptions())).values())
    no_prior = solve_body_batch(sess, BodyOptions(lever_sigma_m=None))
    no_joints = solve_body_batch(sess, BodyOptions(use_joints=False))
    assert no_joints.info["joint_names"] == [] and no_joints.n_quat.shape == no_prior.n_quat.shape
    assert max(joint_errors(sess, no_prior).values()) < 2.0
    assert max(joint_errors(sess, no_joints).values()) > full


def _drifting(sess, rate: float = 0.004, t0: float = 2.0, seed: int = 5):
    """The session with every gyro's bias ramping at `rate` rad/s per s (random direction) after t0."""
    rng = np.random.default_rng(seed)
    sensors, delta = {}, {}
    for n, s in sess.sensors.items():
        d = rng.normal(size=3)
        d *= rate / np.linalg.norm(d)
        b = np.clip(s.t - t0, 0, None)[:, None] * d
        sensors[n], delta[n] = replace(s, gyr=s.gyr + b), b[-1]
    return replace(sess, sensors=sensors), delta


def test_bias_random_walk_absorbs_gyro_drift():
    """Issue 4: a gyro bias drifting by 0.032 rad/s after the N-pose. One constant bias per sensor pushes the
    drift into the joints; bias segments joined by a random walk (the default) track it (the estimated
    change points along the true one) and keep the joints right, in batch, fixed lag and iSAM2."""
    from imugraph.graphs.body_model import bias_segments
    sess, delta = _drifting(chain_session(duration_s=10.0, seed=4))
    const = solve_body_batch(sess, BodyOptions(bias_rw=None))
    walk = solve_body_batch(sess)
    e_c, e_w = max(joint_errors(sess, const).values()), max(joint_errors(sess, walk).values())
    assert e_c > 1.5 and e_w < 1.0 and e_w < 0.5 * e_c
    k2 = int(np.searchsorted(walk.info["kf_t"], 2.0))
    for n, d in delta.items():
        g = walk.info["biases"][n]["gyr_kf"]
        assert g.shape == (walk.info["keyframes"], 3) and np.dot(g[-1] - g[k2], d) > 0
    assert np.array_equal(bias_segments(np.array([0.0, 0.4, 0.9, 1.0, 1.7, 3.2]), 1.0), [0, 0, 0, 1, 1, 2])
    for lag_s in (1.0, None):
        res = solve_body_incremental(sess, lag_s=lag_s, bootstrap_s=5.0)
        assert res.info["failed_updates"] == 0
        assert max(joint_errors(sess, res).values()) < 1.2
