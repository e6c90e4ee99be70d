"""Factors of the body estimator (imugraph.factors.body): argument orders, Jacobians, known answers."""

import gtsam
import numpy as np
import pytest

from imugraph.factors import body as bf
from imugraph.geometry import expmap


def _pose(seed: int) -> gtsam.Pose3:
    rng = np.random.default_rng(seed)
    return gtsam.Pose3(gtsam.Rot3(expmap(rng.normal(0, 1.0, 3))), rng.normal(0, 1.0, 3))


def test_joint_factor_semantics_J_equals_pose_times_lever():
    """J = nTs · l (computed here by hand) gives zero error; the 'natural' order does not."""
    T = _pose(1)
    lever = np.array([0.1, -0.2, 0.3])
    R, p = T.rotation().matrix(), T.translation()
    J = R @ lever + p                                     # independent: nTs · l
    keys = dict(pose=bf.pose_key(0, 0), lever=bf.lever_key(0), joint=bf.joint_key(0, 0))
    v = gtsam.Values()
    v.insert(keys["pose"], T)
    v.insert(keys["lever"], lever)
    v.insert(keys["joint"], J)
    model = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    f1, f2 = bf.joint_factors(keys["joint"], keys["pose"], keys["lever"], keys["pose"], keys["lever"], model)
    assert f1.error(v) < 1e-20 and f2.error(v) < 1e-20
    wrong = gtsam.ReferenceFrameFactorPoint3Pose3(keys["joint"], keys["pose"], keys["lever"], model)
    assert wrong.error(v) > 1.0
    # moving the joint centre by 1 cm along x costs ½ (0.01/0.01)² per factor
    v.update(keys["joint"], J + np.array([0.01, 0, 0]))
    assert f1.error(v) == pytest.approx(0.5, rel=1e-6)


def _num_rot_jac(fun, R, eps=1e-6):
    """Numerical d fun(R·Exp(δ))/dδ, central differences."""
    cols = []
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        cols.append((fun(R @ expmap(d)) - fun(R @ expmap(-d))) / (2 * eps))
    return np.stack(cols, axis=1)


def test_hinge_residual_jacobians_numerical():
    rng = np.random.default_rng(2)
    RP, RC = expmap(rng.normal(0, 1, 3)), expmap(rng.normal(0, 1, 3))
    s_axis = rng.normal(0, 1, 3)
    U = bf.hinge_basis(s_axis)
    a = rng.normal(0, 1, 3)
    a /= np.linalg.norm(a)
    _, HP, HC = bf.hinge_residual(RP, RC, U, a, jacobians=True)
    nP = _num_rot_jac(lambda R: bf.hinge_residual(R, RC, U, a), RP)
    nC = _num_rot_jac(lambda R: bf.hinge_residual(RP, R, U, a), RC)
    np.testing.assert_allclose(HP, nP, atol=1e-7)
    np.testing.assert_allclose(HC, nC, atol=1e-7)


def test_hinge_basis_orthonormal_and_orthogonal_to_axis():
    for axis in ([0, 1, 0], [1, 0, 0], [0.3, -0.2, 0.9]):
        U = bf.hinge_basis(np.array(axis, float))
        np.testing.assert_allclose(U @ U.T, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(U @ np.array(axis, float), 0.0, atol=1e-12)


def test_hinge_factor_zero_for_pure_hinge_and_jacobian_via_gtsam():
    """A child rotated about the parent's lateral axis satisfies the hinge; the CustomFactor's Jacobians
    match numerical derivatives of its error through Pose3.retract."""
    rng = np.random.default_rng(3)
    bRs_P, bRs_C = expmap(rng.normal(0, 0.4, 3)), expmap(rng.normal(0, 0.4, 3))
    nRb_P = expmap(rng.normal(0, 1, 3))
    nRb_C = nRb_P @ expmap(np.array([0.0, 0.7, 0.0]))                    # flexion about y only
    TP = gtsam.Pose3(gtsam.Rot3(nRb_P @ bRs_P), np.zeros(3))
    TC = gtsam.Pose3(gtsam.Rot3(nRb_C @ bRs_C), np.ones(3))
    kP, kC = bf.pose_key(0, 0), bf.pose_key(1, 0)
    f = bf.hinge_factor(gtsam.noiseModel.Isotropic.Sigma(2, 0.05), kP, kC, bRs_P.T, bRs_C.T)
    v = gtsam.Values()
    v.insert(kP, TP)
    v.insert(kC, TC)
    assert f.error(v) < 1e-20
    # off-hinge: abduction of the child
    TC2 = gtsam.Pose3(gtsam.Rot3(nRb_P @ expmap(np.array([0.2, 0.7, 0.0])) @ bRs_C), np.ones(3))
    v.update(kC, TC2)
    assert f.error(v) > 1.0
    lin = f.linearize(v)
    A, b = lin.jacobian()
    eps = 1e-6
    for col in range(12):
        d = np.zeros(12)
        d[col] = eps
        vp, vm = gtsam.Values(), gtsam.Values()
        vp.insert(kP, TP.retract(d[:6]))
        vp.insert(kC, TC2.retract(d[6:]))
        vm.insert(kP, TP.retract(-d[:6]))
        vm.insert(kC, TC2.retract(-d[6:]))
        num = (f.whitenedError(vp) - f.whitenedError(vm)) / (2 * eps)
        np.testing.assert_allclose(A[:, col], num, atol=1e-5)


def test_yaw_prior_weights_heading_and_tilt_separately():
    T = _pose(4)
    f = bf.yaw_information_prior(bf.pose_key(0, 0), T, 1e-3, 0.01, 0.5)
    v = gtsam.Values()
    d = 0.02
    # heading: rotate about the navigation z axis (pre-multiplication): error ½ (d/σ_yaw)²
    v.insert(bf.pose_key(0, 0), gtsam.Pose3(gtsam.Rot3(expmap(np.array([0, 0, d])) @ T.rotation().matrix()),
                                           T.translation()))
    assert f.error(v) == pytest.approx(0.5 * (d / 0.01) ** 2, rel=1e-3)
    v.update(bf.pose_key(0, 0), gtsam.Pose3(gtsam.Rot3(expmap(np.array([d, 0, 0])) @ T.rotation().matrix()),
                                           T.translation()))
    assert f.error(v) == pytest.approx(0.5 * (d / 0.5) ** 2, rel=1e-3)


def test_preintegrate_constant_rate_known_rotation():
    n, dt = 30, 0.01
    w = np.array([0.3, -0.2, 0.5])
    gyr = np.tile(w, (n, 1))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    kf = np.array([0, 10, 20, 29])
    prm = bf.imu_params(9.81, np.full(3, 1e-3), np.full(3, 1e-2), dt)
    pims = bf.preintegrate(gyr, acc, np.full(n, dt), kf, prm, gtsam.imuBias.ConstantBias())
    assert len(pims) == 3
    np.testing.assert_allclose(pims[0].deltaRij().matrix(), expmap(w * 10 * dt), atol=1e-12)
    np.testing.assert_allclose(pims[2].deltaTij(), 9 * dt, atol=1e-12)


def test_keys_distinct_and_dims():
    ks = [bf.pose_key(1, 2), bf.pose_key(2, 1), bf.vel_key(1, 2), bf.joint_key(1, 2), bf.lever_key(3), bf.bias_key(3)]
    assert len(set(ks)) == len(ks)
    assert [bf.key_dim(k) for k in ks] == [6, 6, 3, 3, 3, 6]


def test_mag_factor_zero_when_consistent():
    T = _pose(5)
    n_dir = np.array([0.5, 0.0, -0.866])
    b_mag = T.rotation().matrix().T @ (n_dir / np.linalg.norm(n_dir))
    f = bf.mag_factor(bf.pose_key(0, 0), b_mag, 1.0, n_dir, gtsam.noiseModel.Isotropic.Sigma(3, 0.05))
    v = gtsam.Values()
    v.insert(bf.pose_key(0, 0), T)
    assert f.error(v) < 1e-20
