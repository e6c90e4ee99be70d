"""Soft axial sensor-to-segment rotation (imugraph.factors.body_axial, graphs.body_axial): Jacobians vs numerical
derivatives, known answers computed independently of the code under test, and the option on a small graph."""

import gtsam
import numpy as np
import pytest

from factor_jacobians import assert_jacobians_match_numerical
from imugraph.factors import body as bf
from imugraph.factors import body_axial as ba
from imugraph.geometry import expmap


def _rot(rng, s=1.0):
    return expmap(rng.normal(0, s, 3))


def _num(fun, x0, eps=1e-6):
    """Central-difference derivative of fun at x0 along each coordinate (columns)."""
    x0 = np.atleast_1d(np.asarray(x0, float))
    cols = []
    for i in range(x0.size):
        d = np.zeros_like(x0)
        d[i] = eps
        cols.append((fun(x0 + d) - fun(x0 - d)) / (2 * eps))
    return np.stack(cols, axis=1)


def test_axial_hinge_residual_jacobians_numerical():
    rng = np.random.default_rng(4)
    RP, RC, B_P, B_C = _rot(rng), _rot(rng), _rot(rng), _rot(rng)
    a_P, a_C = rng.normal(0, 1, 3), rng.normal(0, 1, 3)
    a_P, a_C = a_P / np.linalg.norm(a_P), a_C / np.linalg.norm(a_C)
    tP, tC = 0.3, -0.2
    _, HP, HC, dP, dC = ba.axial_hinge_residual(RP, RC, B_P, B_C, a_P, a_C, tP, tC, jacobians=True)
    f = ba.axial_hinge_residual
    np.testing.assert_allclose(HP, _num(lambda d: f(RP @ expmap(d), RC, B_P, B_C, a_P, a_C, tP, tC), np.zeros(3)),
                               atol=1e-7)
    np.testing.assert_allclose(HC, _num(lambda d: f(RP, RC @ expmap(d), B_P, B_C, a_P, a_C, tP, tC), np.zeros(3)),
                               atol=1e-7)
    np.testing.assert_allclose(dP, _num(lambda t: f(RP, RC, B_P, B_C, a_P, a_C, t[0], tC), [tP])[:, 0], atol=1e-7)
    np.testing.assert_allclose(dC, _num(lambda t: f(RP, RC, B_P, B_C, a_P, a_C, tP, t[0]), [tC])[:, 0], atol=1e-7)


def test_axial_hinge_known_answer_thigh_turned_about_long_axis():
    """Segments: thigh nRb_P = Rz(γ) (turned about its long axis z), shank nRb_C = Ry(α) (pure flexion) with
    sensors at bRs0. The child's axis in the parent frame is Rz(−γ) y = (sin γ, cos γ, 0): residual
    (sin γ, 0), computed here by hand. θ_P = γ (the sensor turned with the skin, the segment did not) cancels it."""
    rng = np.random.default_rng(1)
    B_P, B_C = _rot(rng), _rot(rng)
    z = np.array([0.0, 0.0, 1.0])
    g, alpha = 0.2, 0.7
    nRb_P, nRb_C = expmap(g * z), expmap(alpha * np.array([0.0, 1.0, 0.0]))
    RP, RC = nRb_P @ B_P, nRb_C @ B_C                      # nRs = nRb bRs0
    e = ba.axial_hinge_residual(RP, RC, B_P, B_C, z, -z, 0.0, 0.0)
    np.testing.assert_allclose(e, [np.sin(g), 0.0], atol=1e-12)
    # the same sensor reading explained by a sensor turned by θ_P = γ on an unturned thigh: zero residual
    np.testing.assert_allclose(ba.axial_hinge_residual(RP, RC, B_P, B_C, z, -z, g, 0.0), [0.0, 0.0], atol=1e-12)
    # θ on the child side: the shank's sensor turned by θ_C = 0.1 about the shank's long axis â_C = −z,
    # nRs_C = nRb_C Exp(θ_C â_C) bRs0 (S1): a rigid model (θ_C = 0) sees a broken hinge, the soft one does not
    RC3 = nRb_C @ expmap(0.1 * -z) @ B_C
    assert np.linalg.norm(ba.axial_hinge_residual(RP, RC3, B_P, B_C, z, -z, g, 0.0)) > 0.05
    np.testing.assert_allclose(ba.axial_hinge_residual(RP, RC3, B_P, B_C, z, -z, g, 0.1), [0.0, 0.0], atol=1e-12)


def test_axial_hinge_factor_jacobians_via_gtsam():
    rng = np.random.default_rng(7)
    B_P, B_C = _rot(rng), _rot(rng)
    z = np.array([0.0, 0.0, -1.0])
    keys = [bf.pose_key(0, 3), bf.pose_key(1, 3), ba.axial_key(0, 3), ba.axial_offset_key(0), ba.axial_key(1, 3)]
    f = ba.axial_hinge_factor(gtsam.noiseModel.Diagonal.Sigmas(np.array([0.07, 0.023])), keys[0], keys[1], B_P, B_C,
                              z, z, theta_P=(keys[2], keys[3]), theta_C=(keys[4],))
    v = gtsam.Values()
    v.insert(keys[0], gtsam.Pose3(gtsam.Rot3(_rot(rng)), rng.normal(0, 1, 3)))
    v.insert(keys[1], gtsam.Pose3(gtsam.Rot3(_rot(rng)), rng.normal(0, 1, 3)))
    for k, th in zip(keys[2:], (0.1, -0.05, 0.2)):
        v.insert(k, np.array([th]))
    assert_jacobians_match_numerical(f, v, keys, [6, 6, 1, 1, 1])


def test_gauss_markov_link_stationary_variance_and_jacobian():
    """(S2): var(φ_k − ρ φ_{k−1}) = σ²(1 − ρ²) keeps var φ_k = σ² for any spacing (checked by hand here)."""
    sigma, tau, dt = 0.1, 0.1, 0.06
    f = ba.gauss_markov_link(ba.axial_key(0, 0), ba.axial_key(0, 1), dt, sigma, tau)
    rho = np.exp(-dt / tau)
    v = gtsam.Values()
    v.insert(ba.axial_key(0, 0), np.array([0.3]))
    v.insert(ba.axial_key(0, 1), np.array([0.1]))
    e = 0.1 - rho * 0.3
    assert f.error(v) == pytest.approx(0.5 * e**2 / (sigma**2 * (1 - rho**2)), rel=1e-9)
    A, b = f.linearize(v).jacobian()
    s = sigma * np.sqrt(1 - rho**2)
    np.testing.assert_allclose(A, [[-rho / s, 1.0 / s]], rtol=1e-9)
    assert rho**2 * sigma**2 + s**2 == pytest.approx(sigma**2)


def test_long_axis_of_lower_body_thigh_points_down():
    from imugraph.body.skeleton import lower_body
    np.testing.assert_allclose(ba.long_axis(lower_body(), "LeftUpperLeg"), [0.0, 0.0, -1.0], atol=1e-12)


def _sta_session(theta_amp_deg: float, seed: int = 4, duration_s: float = 8.0):
    """tests/body_synth chain (hinge knee) whose shank sensor turns about the shank's long axis â = ends/|ends|:
    bRs(t) = Exp(θ(t) â) bRs0, θ(t) = A·env(t)·sin(2π 0.8 t) (a soft-tissue artefact; truth computed here)."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from body_synth import MiniBodySession, _envelope, _poses, chain_skeleton

    from imugraph.body.placement import nominal_placement
    from imugraph.geometry import logmap, rotmat_to_quat
    from imugraph.sim.sensors import SensorParams, simulate_imu

    skel = chain_skeleton()
    rng = np.random.default_rng(seed + 1000)
    rate, npose = 60.0, 2.0
    dt = 1.0 / rate
    t = np.arange(int(duration_s * rate)) * dt

    def poses(tt):
        return _poses(tt, skel, _envelope(tt, npose), seed, 35.0, True, True)

    def theta(tt):
        return np.deg2rad(theta_amp_deg) * _envelope(tt, npose) * np.sin(2 * np.pi * 0.8 * tt)

    def nRs_of(RR, tt, i, name, bRs0):
        if name != "RightLowerLeg":
            return RR[:, i] @ bRs0
        a = np.asarray(skel.ends[i], float) / np.linalg.norm(skel.ends[i])
        return RR[:, i] @ expmap(theta(tt)[:, None] * a) @ bRs0

    R, p = poses(t)
    R1, _ = poses(t + dt)
    h, tm = 1e-3, t + dt / 2
    (Rc, pm), (Rp, pp), (Rm, pn) = poses(tm), poses(tm + h), poses(tm - h)
    sensors = {}
    for name in skel.sensed:
        i = skel.index(name)
        nom = nominal_placement(skel, name)
        ax = rng.standard_normal(3)
        bRs0 = nom.bRs @ expmap(ax / np.linalg.norm(ax) * np.deg2rad(10.0))
        nRs, nRs1 = nRs_of(R, t, i, name, bRs0), nRs_of(R1, t + dt, i, name, bRs0)
        w = logmap(np.swapaxes(nRs, 1, 2) @ nRs1) / dt
        pos = lambda RR, PP: PP[:, i] + np.einsum("tij,j->ti", RR[:, i], nom.b_pos)   # noqa: E731  (on the axis side)
        n_acc = (pos(Rp, pp) - 2 * pos(Rc, pm) + pos(Rm, pn)) / h**2
        prm = SensorParams(gyro_bias=rng.normal(0, 0.005, 3), gyro_noise=0.004, acc_noise=0.04)
        ses = simulate_imu(t, rotmat_to_quat(nRs), w, n_acc, prm, rng, name=name)
        sensors[name] = ses.with_mag(np.full_like(ses.mag, np.nan))
    truth = {"n_quat": rotmat_to_quat(R), "n_pos": p, "names": list(skel.names)}
    return MiniBodySession(t=t, sensors=sensors, skeleton=skel, truth=truth), theta(t)


def _knee_error_deg(sess, res) -> float:
    from imugraph.geometry import quat_conj, quat_mul, quat_to_rotvec
    tq, skel = sess.truth["n_quat"], sess.skeleton
    p, i = skel.index("RightUpperLeg"), skel.index("RightLowerLeg")
    rt = quat_mul(quat_conj(tq[:, p]), tq[:, i])
    re = quat_mul(quat_conj(res.n_quat[:, p]), res.n_quat[:, i])
    return float(np.rad2deg(np.sqrt(np.mean(np.sum(quat_to_rotvec(quat_mul(quat_conj(rt), re)) ** 2, 1)))))


def test_soft_axial_shank_recovers_injected_artefact():
    """A shank sensor turning ±8° about the shank (hinge knee in the truth): the rigid model carries the turn
    into the knee; the soft axial rotation with the knee hinge takes most of it out, and θ follows it."""
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions

    sess, theta = _sta_session(8.0)
    rigid = solve_body_batch(sess, BodyOptions(hinges=("RightLowerLeg",)))
    soft = solve_body_batch(sess, BodyOptions(hinges=("RightLowerLeg",), axial_segments=("RightLowerLeg",)))
    e_rigid, e_soft = _knee_error_deg(sess, rigid), _knee_error_deg(sess, soft)
    assert e_rigid > 3.0                             # the artefact is visible to the rigid model
    assert e_soft < 0.6 * e_rigid
    assert len(soft.info["passes"]) == 2 and "RightLowerLeg" in soft.info["axial_theta"]
    th = soft.info["axial_theta"]["RightLowerLeg"]
    moving = theta != 0
    assert np.corrcoef(th[moving], theta[moving])[0, 1] > 0.8          # θ(t) follows the injected turn
    assert rigid.info["axial_theta"] == {}


def test_soft_axial_without_artefact_changes_little():
    """Rigid sensors (no artefact): the option must not hurt (simulated sensors have no soft tissue)."""
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions

    sess, _ = _sta_session(0.0, seed=5)
    base = solve_body_batch(sess, BodyOptions(hinges=("RightLowerLeg",)))
    soft = solve_body_batch(sess, BodyOptions(hinges=("RightLowerLeg",), axial_segments=("RightLowerLeg",)))
    assert _knee_error_deg(sess, soft) < max(1.0, 1.2 * _knee_error_deg(sess, base))


def test_axial_segment_without_sensor_raises_session_error():
    from imugraph.errors import SessionError
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions

    sess, _ = _sta_session(0.0, seed=5, duration_s=4.0)
    with pytest.raises(SessionError, match="axial_segments"):
        solve_body_batch(sess, BodyOptions(hinges=("RightLowerLeg",), axial_segments=("LeftLowerLeg",)))
