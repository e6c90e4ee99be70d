"""smooth_fixed with the batch / stream model's nav-field perturbation d_k (imugraph.graphs.cpp_field): the
vectorised magnetometer block against numerical derivatives and against the stream's own factors
(stream_field eq. 3, stream_calstate eq. 1–2), and the whole solve against gtsam's Levenberg–Marquardt on
the same graph built from the stream's CustomFactors."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

import imugraph.graphs.cpp_smoother as cs
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.factors.field import field_key
from imugraph.factors.gyro import keyframe_layout
from imugraph.geometry import expmap, quat_to_rotmat
from imugraph.graphs.cpp_field import FieldMagBlock, huber_cost
from imugraph.graphs.cpp_velocity import pose_key, robust
from imugraph.graphs.stream_calstate import cal_mag_jacobians
from imugraph.graphs.stream_field import field_mag_factor, field_start_prior, field_step_factor
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu

SIG_D = (0.015, 0.003, 0.015)
N_MAG = np.array([np.cos(1.1), 0.0, -np.sin(1.1)])


def _values(rng, K):
    x = gtsam.Values()
    for k in range(K):
        x.insert(pose_key(k), gtsam.Pose3(gtsam.Rot3(expmap(rng.normal(size=3))), rng.normal(size=3)))
        x.insert(field_key(k), rng.normal(scale=0.02, size=3))
    return x


def _block(rng, K, raw: bool, huber_k):
    rows = np.arange(K)
    A = (np.eye(3) + 0.1 * rng.normal(size=(K, 3, 3))) if raw else np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
    L = np.eye(3) * 0.01 + 0.002 * np.tril(rng.normal(size=(K, 3, 3)))
    return FieldMagBlock(rows, A, rng.normal(size=(K, 3)) * 0.1 + N_MAG, np.linalg.inv(L), N_MAG, huber_k, True, K)


@pytest.mark.parametrize("raw", [False, True])
def test_block_jacobians_are_numerical_derivatives(raw):
    """H_pose (gtsam's retraction, [ω, v]) and H_d against central differences of the whitened residual."""
    rng = np.random.default_rng(11)
    K = 4
    blk, x = _block(rng, K, raw, None), _values(rng, K)
    H_pose, H_d, rhs = blk.jacobians(x)

    def r(values):
        return np.einsum("kij,kj->ki", blk.W, blk.errors(values))

    np.testing.assert_allclose(rhs, -r(x), atol=1e-12)
    h = 1e-6
    for k in range(K):
        for i in range(6):
            xp, xm = gtsam.Values(x), gtsam.Values(x)
            for xx, s in ((xp, h), (xm, -h)):
                xx.update(pose_key(k), x.atPose3(pose_key(k)).retract(s * np.eye(6)[i]))
            num = (r(xp) - r(xm)) / (2 * h)
            np.testing.assert_allclose(H_pose[k][:, i], num[k], rtol=1e-5, atol=1e-4)
            assert np.allclose(np.delete(num, k, axis=0), 0.0)
        for i in range(3):
            xp, xm = gtsam.Values(x), gtsam.Values(x)
            xp.update(field_key(k), x.atVector(field_key(k)) + h * np.eye(3)[i])
            xm.update(field_key(k), x.atVector(field_key(k)) - h * np.eye(3)[i])
            np.testing.assert_allclose(H_d[k][:, i], ((r(xp) - r(xm)) / (2 * h))[k], rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("huber_k", [None, 2.0, 0.05])
def test_calibrated_block_is_the_stream_field_factor(huber_k):
    """Mode "calibrated" (A = I): error, cost and Huber-weighted linearisation equal gtsam's own of the stream's
    CustomFactor (stream_field.field_mag_factor) with the same robust Gaussian noise model (0.05: Huber active)."""
    rng = np.random.default_rng(3)
    K = 5
    blk, x = _block(rng, K, False, huber_k), _values(rng, K)
    H_pose, H_d, rhs = blk.jacobians(x)
    cost = 0.0
    for k in range(K):
        f = field_mag_factor(pose_key(k), field_key(k), blk.b[k], N_MAG,
                             robust(gtsam.noiseModel.Gaussian.Information(blk.W[k].T @ blk.W[k]), huber_k))
        np.testing.assert_allclose(f.unwhitenedError(x), blk.errors(x)[k], atol=1e-12)
        cost += f.error(x)
        Ab = f.linearize(x).augmentedJacobian()        # [H_pose | H_d | b], same square root W up to sign
        mine = np.hstack([H_pose[k], H_d[k], rhs[k][:, None]])
        np.testing.assert_allclose(Ab.T @ Ab, mine.T @ mine, atol=1e-6 * max(1.0, np.abs(mine.T @ mine).max()))
    assert blk.cost(x) == pytest.approx(cost, rel=1e-10)


def test_raw_block_is_the_stream_calstate_factor():
    """Mode "raw" (A = D M_k, b = ȳ − o): error and Jacobians equal stream_calstate.cal_mag_jacobians' at fixed θ."""
    rng = np.random.default_rng(5)
    D, o, dip = np.eye(3) * 40 + rng.normal(size=(3, 3)), rng.normal(size=3) * 5, 1.1
    M = expmap(rng.normal(scale=0.05, size=3)).T
    y_avg = rng.normal(size=3) * 40
    R, d = expmap(rng.normal(size=3)), rng.normal(scale=0.01, size=3)
    blk = FieldMagBlock([0], (D @ M)[None], (y_avg - o)[None], np.eye(3)[None], N_MAG, None, True, 1)
    x = gtsam.Values()
    x.insert(pose_key(0), gtsam.Pose3(gtsam.Rot3(R), np.zeros(3)))
    x.insert(field_key(0), d)
    e, J_pose, J_d, _ = cal_mag_jacobians(R, d, np.r_[D.ravel(), o, dip], M, y_avg)
    H_pose, H_d, rhs = blk.jacobians(x)
    np.testing.assert_allclose(-rhs[0], e, atol=1e-9)
    np.testing.assert_allclose(H_pose[0], J_pose, atol=1e-9)
    np.testing.assert_allclose(H_d[0], J_d, atol=1e-9)


def test_huber_cost_is_gtsams():
    """huber_cost equals the error gtsam gives a factor with a Huber-robust unit noise model."""
    mdl = robust(gtsam.noiseModel.Unit.Create(1), 1.5)
    z = gtsam.symbol("z", 0)
    f = gtsam.PriorFactorVector(z, np.zeros(1), mdl)
    for r in (0.3, 1.5, 4.0):
        x = gtsam.Values()
        x.insert(z, np.array([r]))
        assert huber_cost(np.array([r]), 1.5)[0] == pytest.approx(f.error(x), rel=1e-12)


def _perturbed_session(seed: int):
    """30 s at 100 Hz whose nav field wanders (d(t): 0.04 vertical, 0.01 across, 0.03 along, periods 5–9 s)."""
    rng = np.random.default_rng(seed)
    motion = random_rotation_motion(30.0, 100.0, rng, rms_rate=0.8, translation_m=0.1, pauses=1)
    prm = SensorParams(gyro_bias=np.array([0.01, -0.005, 0.008]), gyro_noise=np.full(3, 0.005),
                       acc_noise=np.full(3, 0.05), mag_noise=np.full(3, 0.3), field_norm=50.0,
                       dip_rad=1.1, g=9.81)
    s = simulate_imu(motion.t, motion.nRb, motion.b_omega, motion.n_acc, prm, rng)
    t = s.t - s.t[0]
    d = np.stack([0.03 * np.sin(2 * np.pi * t / 7), 0.01 * np.sin(2 * np.pi * t / 9), 0.04 * np.cos(2 * np.pi * t / 5)], 1)
    bRn = np.transpose(quat_to_rotmat(s.quat), (0, 2, 1))
    mag = np.einsum("nij,nj->ni", bRn, prm.n_mag + d) @ prm.D_unit.T + prm.mag_o + rng.normal(size=(s.n, 3)) * 0.3
    cal = Calibration(D=prm.D_unit, o=prm.mag_o, dip_deg=float(np.rad2deg(prm.dip_rad)), gyro_bias=prm.gyro_bias,
                      noise={"gyr": prm.gyro_noise, "acc": prm.acc_noise, "mag": prm.mag_noise})
    return replace(s, mag=mag), cal


def _rms_deg(q, q_ref):
    R, R_ref = quat_to_rotmat(q), quat_to_rotmat(q_ref)
    c = np.clip((np.einsum("nij,nij->n", R, R_ref) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.rad2deg(np.sqrt(np.mean(np.arccos(c) ** 2))))


def test_field_solve_equals_gtsam_lm_on_the_stream_factors(monkeypatch):
    """The whole field_sigma solve against gtsam's own Levenberg–Marquardt on the same C++ velocity graph plus,
    built here sample by sample, the stream's CustomFactor per keyframe (stream_field eq. 3: m̄_k and its full
    covariance) and the d_k prior (stream_field.field_start_prior / field_step_factor). The field wanders, so
    ignoring d_k moves the answer far more than the tolerance."""
    s, cal = _perturbed_session(7)
    seen = {}
    real = cs._same_model_solve

    def spy(graph, values, ordering, pre, y, *rest):
        seen.update(graph=graph, values=values, pre=pre, y=y)
        return real(graph, values, ordering, pre, y, *rest)

    monkeypatch.setattr(cs, "_same_model_solve", spy)
    q_field = cs.smooth_fixed(s, cal, keyframe_hz=5.0, field_sigma=SIG_D, field_tau=1.0)
    q_plain = cs.smooth_fixed(s, cal, keyframe_hz=5.0)
    pre, y = seen["pre"], seen["y"]
    K = len(pre.kf_samples)
    D_inv = np.linalg.inv(cal.D)
    sig_y = np.asarray(cal.noise["mag"], float)
    graph = gtsam.NonlinearFactorGraph()
    graph.push_back(seen["graph"])
    x0 = gtsam.Values(seen["values"])
    for k in range(K):
        idx = [j for j in range(s.n) if pre.sample_kf[j] == k]
        m = [pre.kRb[j] @ D_inv @ (y[j] - cal.o) for j in idx]
        cov = sum(pre.kRb[j] @ D_inv @ np.diag(sig_y**2) @ D_inv.T @ pre.kRb[j].T for j in idx) / len(idx) ** 2
        graph.add(field_mag_factor(pose_key(k), field_key(k), np.mean(m, axis=0), cal.n_mag,
                                   robust(gtsam.noiseModel.Gaussian.Covariance(cov), 2.0)))
        x0.insert(field_key(k), np.zeros(3))
        if k < K - 1:
            graph.add(field_step_factor(field_key(k), field_key(k + 1), float(pre.dt[k]), SIG_D, 1.0))
    graph.add(field_start_prior(field_key(0), SIG_D))
    prm = gtsam.LevenbergMarquardtParams()
    prm.setRelativeErrorTol(1e-10)
    prm.setMaxIterations(100)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, x0, prm).optimize()
    nRk = gtsam.utilities.extractPose3(ref)[:K, :9].reshape(-1, 3, 3)
    q_ref = cs.sample_orientations(nRk, pre)
    gap_plain = _rms_deg(q_plain, q_ref)
    print(f"field vs gtsam LM {_rms_deg(q_field, q_ref):.2e}°, plain vs it {gap_plain:.3f}°, truth field "
          f"{_rms_deg(q_field, s.quat):.3f}° plain {_rms_deg(q_plain, s.quat):.3f}°")
    assert gap_plain > 0.3                                   # the premise: d_k matters here
    assert _rms_deg(q_field, q_ref) < min(0.01, 0.05 * gap_plain)
    assert _rms_deg(q_field, s.quat) < _rms_deg(q_plain, s.quat)


def test_mag_offsets_and_bad_options_are_one_line_errors():
    s, cal = _perturbed_session(2)
    part = s.slice(0, 400)
    for kw, field in ((dict(mag_model="bogus"), "mag_model"), (dict(mag_offsets=np.zeros((3, 3))), "mag_offsets"),
                      (dict(field_sigma=0.01, linear_acceleration="noise"), "linear_acceleration")):
        with pytest.raises(SessionError) as info:
            cs.smooth_fixed(part, cal, **kw)
        assert field in str(info.value) and "\n" not in str(info.value)


def test_mag_offsets_undo_an_added_offset():
    """A raw-field offset added to the samples of some keyframes and given back as mag_offsets gives the
    undisturbed answer (raw model); not given back, the answer moves."""
    s, cal = _perturbed_session(3)
    kf, skf = keyframe_layout(s.n, 20)                 # keyframe_hz 5 at 100 Hz
    off = np.zeros((len(kf), 3))
    off[40:60] = [30.0, -20.0, 10.0]
    hit = replace(s, mag=s.mag + off[skf])
    q0 = cs.smooth_fixed(s, cal, keyframe_hz=5.0, mag_model="raw", field_sigma=SIG_D)
    q1 = cs.smooth_fixed(hit, cal, keyframe_hz=5.0, mag_model="raw", field_sigma=SIG_D, mag_offsets=off)
    q2 = cs.smooth_fixed(hit, cal, keyframe_hz=5.0, mag_model="raw", field_sigma=SIG_D)
    assert _rms_deg(q1, q0) < 1e-6
    assert _rms_deg(q2, q0) > 0.1
