"""Thigh-sensor turn proportional to the knee flexion (imugraph.factors.knee_sta): the hinge factor's Jacobians vs
numerical derivatives, a known answer built independently of the code under test, the two-stage estimator (G4)
recovering an injected gain, and the option off = the default solve untouched."""

from types import SimpleNamespace

import gtsam
import numpy as np

from factor_jacobians import assert_jacobians_match_numerical
from imugraph.body.skeleton import lower_body
from imugraph.factors import body as bf
from imugraph.factors import knee_sta as ks
from imugraph.geometry import expmap, quat_to_rotmat, rotmat_to_quat
from imugraph.graphs.body_model import BodyOptions

Z_DOWN = np.array([0.0, 0.0, -1.0])


def _rot(rng, s=1.0):
    return expmap(rng.normal(0, s, 3))


def test_gain_hinge_factor_jacobians_via_gtsam():
    rng = np.random.default_rng(21)
    B_P, B_C = _rot(rng), _rot(rng)
    keys = [bf.pose_key(0, 5), bf.pose_key(1, 5), ks.offset_key(0, 5), ks.gain_key(0)]
    f = ks.gain_hinge_factor(gtsam.noiseModel.Diagonal.Sigmas(np.array([0.07, 0.023])), keys[0], keys[1], B_P, B_C,
                             Z_DOWN, Z_DOWN, keys[2], keys[3], kappa=0.7)
    v = gtsam.Values()
    v.insert(keys[0], gtsam.Pose3(gtsam.Rot3(_rot(rng)), rng.normal(0, 1, 3)))
    v.insert(keys[1], gtsam.Pose3(gtsam.Rot3(_rot(rng)), rng.normal(0, 1, 3)))
    v.insert(keys[2], np.array([0.12]))
    v.insert(keys[3], np.array([-0.3]))
    A = assert_jacobians_match_numerical(f, v, keys, [6, 6, 1, 1])
    assert np.abs(A[:, -1]).max() > 1e-3                   # g really enters (κ ≠ 0)


def test_gain_hinge_zero_exactly_when_c_plus_g_kappa_is_the_sensor_turn():
    """Thigh sensor turned by θ0 about the thigh's long axis on a perfect hinge knee (shank = thigh · Ry(flexion)):
    the residual vanishes for c + g κ = θ0 and not otherwise."""
    rng = np.random.default_rng(3)
    R_T = _rot(rng)
    R_S = R_T @ expmap(np.array([0.0, 0.9, 0.0]))            # knee flexed 0.9 rad about y
    theta0 = 0.25
    nRs_P = R_T @ expmap(theta0 * Z_DOWN)                     # (S1) with bRs0 = I: nRs = nRb Exp(θ0 â)
    keys = [bf.pose_key(0, 0), bf.pose_key(1, 0), ks.offset_key(0, 0), ks.gain_key(0)]
    kappa = 0.9
    f = ks.gain_hinge_factor(gtsam.noiseModel.Unit.Create(2), keys[0], keys[1], np.eye(3), np.eye(3), Z_DOWN, Z_DOWN,
                             keys[2], keys[3], kappa)

    def err(c, g):
        v = gtsam.Values()
        v.insert(keys[0], gtsam.Pose3(gtsam.Rot3(nRs_P), np.zeros(3)))
        v.insert(keys[1], gtsam.Pose3(gtsam.Rot3(R_S), np.zeros(3)))
        v.insert(keys[2], np.array([c]))
        v.insert(keys[3], np.array([g]))
        return f.unwhitenedError(v)

    np.testing.assert_allclose(err(0.25, 0.0), 0.0, atol=1e-12)
    np.testing.assert_allclose(err(0.07, 0.2), 0.0, atol=1e-12)          # 0.07 + 0.2 · 0.9 = 0.25
    assert np.linalg.norm(err(0.0, 0.0)) > 0.1


def _fake(n=1500, fs=100.0, g_true=-0.1, c_true=0.05, seed=0):
    """A lower-body output whose left thigh is turned about its long axis by c + g κ (a sensor on soft tissue)
    over a pure-hinge knee; returns (pb, res, true thigh quaternions)."""
    skel = lower_body()
    t = np.arange(n) / fs
    kappa = np.deg2rad(30.0) * (1.0 - np.cos(2 * np.pi * 0.7 * t))
    rng = np.random.default_rng(seed)
    w = np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0)       # slowly wandering thigh
    R_T = np.stack([expmap(x) for x in w])
    R_S = R_T @ np.stack([expmap(np.array([0.0, k, 0.0])) for k in kappa])
    theta = c_true + g_true * kappa
    R_T_out = R_T @ np.stack([expmap(th * Z_DOWN) for th in theta])     # rigid output nRs bRs0ᵀ = nRb Exp(θ â) (S1)
    q = np.tile(np.array([1.0, 0, 0, 0]), (n, len(skel.names), 1))
    q[:, skel.index("LeftUpperLeg")] = rotmat_to_quat(R_T_out)
    q[:, skel.index("LeftLowerLeg")] = rotmat_to_quat(R_S)
    opts = BodyOptions(knee_gain_segments=("LeftUpperLeg",), knee_gain_mode="two-stage", knee_gain_apply="offset+gain")
    pb = SimpleNamespace(opts=opts, joints=[SimpleNamespace(parent="LeftUpperLeg", child="LeftLowerLeg")], skel=skel,
                         kf=np.arange(0, n, 6), session=SimpleNamespace(t=t))
    res = SimpleNamespace(names=tuple(skel.names), n_quat=q, info={})
    return pb, res, R_T


def test_two_stage_recovers_injected_gain_and_the_thigh():
    pb, res, R_T = _fake()
    i = res.names.index("LeftUpperLeg")
    err0 = np.arccos(np.clip((np.trace(np.swapaxes(R_T, 1, 2) @ quat_to_rotmat(res.n_quat[:, i]), axis1=1, axis2=2)
                              - 1) / 2, -1, 1))
    ks.apply_to_result(pb, gtsam.Values(), res)
    g = res.info["knee_gain"]["LeftUpperLeg"]["gain"]
    assert abs(g - (-0.1)) < 0.01
    err1 = np.arccos(np.clip((np.trace(np.swapaxes(R_T, 1, 2) @ quat_to_rotmat(res.n_quat[:, i]), axis1=1, axis2=2)
                              - 1) / 2, -1, 1))
    assert np.sqrt(np.mean(err0 ** 2)) > np.deg2rad(1.5)
    assert np.sqrt(np.mean(err1 ** 2)) < np.deg2rad(0.3)     # the thigh back on the femur


def test_two_stage_no_artefact_gives_zero_gain():
    pb, res, _ = _fake(g_true=0.0, c_true=0.0)
    ks.apply_to_result(pb, gtsam.Values(), res)
    assert abs(res.info["knee_gain"]["LeftUpperLeg"]["gain"]) < 1e-3


def test_option_off_by_default():
    o = BodyOptions()
    assert o.knee_gain_segments == ()
    pb = SimpleNamespace(opts=o, joints=[SimpleNamespace(parent="LeftUpperLeg", child="LeftLowerLeg")],
                         bRs_fixed={}, names=["LeftUpperLeg", "LeftLowerLeg"])
    assert not ks.handles(pb, pb.joints[0])
    assert ks.factors_at(pb, 0).size() == 0
