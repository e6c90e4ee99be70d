"""Every factor's Jacobians against numerical derivatives; preintegration against GTSAM's own."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.factors.accelerometer import accelerometer_factor
from imugraph.factors.gyro import ahrs_factors, keyframe_layout, preintegrate, right_jacobian
from imugraph.factors.magnetometer import magnetometer_factor
from imugraph.factors.theta import pack_theta
from imugraph.geometry import expmap


def _numerical_jacobian(factor, values, key_kinds, h=1e-6):
    """Columns of d(unwhitened error)/d(tangent) for each key, by central differences."""
    cols = []
    for key, kind in key_kinds:
        dim = 3 if kind == "rot" else len(values.atVector(key))
        for i in range(dim):
            d = np.zeros(dim); d[i] = h
            plus, minus = gtsam.Values(values), gtsam.Values(values)
            if kind == "rot":
                R = values.atRot3(key)
                plus.update(key, R.retract(d)); minus.update(key, R.retract(-d))
            else:
                v = values.atVector(key)
                plus.update(key, v + d); minus.update(key, v - d)
            cols.append((factor.unwhitenedError(plus) - factor.unwhitenedError(minus)) / (2 * h))
    return np.stack(cols, axis=1)


def _analytic(factor, values, sigmas):
    A, _ = factor.linearize(values).jacobian()
    return A * sigmas[:, None]          # undo whitening (diagonal model)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_magnetometer_jacobians(rng):
    K = 6
    kRb = expmap(rng.normal(0, 0.3, (K, 3)))
    D = np.eye(3) * 40 + rng.normal(0, 3, (3, 3))
    theta = pack_theta(D, rng.normal(0, 5, 3), np.deg2rad(65))
    sigma = np.array([0.5, 0.7, 0.9])
    f = magnetometer_factor(keys.rot(0), keys.CALIB, kRb, rng.normal(0, 40, (K, 3)), sigma)
    v = gtsam.Values()
    v.insert(keys.rot(0), gtsam.Rot3.Expmap(rng.normal(0, 1, 3)))
    v.insert(keys.CALIB, theta)
    num = _numerical_jacobian(f, v, [(keys.rot(0), "rot"), (keys.CALIB, "vec")])
    ana = _analytic(f, v, np.tile(sigma, K))
    assert ana.shape == (3 * K, 16)
    np.testing.assert_allclose(ana, num, atol=1e-5 * np.abs(num).max())


def test_accelerometer_jacobians(rng):
    K = 5
    kRb = expmap(rng.normal(0, 0.3, (K, 3)))
    sigma = np.array([0.1, 0.2, 0.3])
    f = accelerometer_factor(keys.rot(3), kRb, rng.normal(0, 9.81, (K, 3)), sigma, 9.81)
    v = gtsam.Values()
    v.insert(keys.rot(3), gtsam.Rot3.Expmap(rng.normal(0, 1, 3)))
    num = _numerical_jacobian(f, v, [(keys.rot(3), "rot")])
    np.testing.assert_allclose(_analytic(f, v, np.tile(sigma, K)), num, atol=1e-6 * np.abs(num).max())


def test_magnetometer_residual_zero_on_model(rng):
    """The model y = D ΔRᵀ R_kᵀ n + o gives zero residual for noise-free data."""
    K = 4
    kRb = expmap(rng.normal(0, 0.3, (K, 3)))
    nRk = gtsam.Rot3.Expmap(rng.normal(0, 1, 3))
    D, o, dip = np.diag([30.0, 45.0, 50.0]), np.array([1.0, -2.0, 3.0]), np.deg2rad(60)
    n = np.array([np.cos(dip), 0, -np.sin(dip)])
    y = np.stack([D @ (nRk.matrix() @ kRb[j]).T @ n + o for j in range(K)])
    f = magnetometer_factor(keys.rot(0), keys.CALIB, kRb, y, np.ones(3))
    v = gtsam.Values(); v.insert(keys.rot(0), nRk); v.insert(keys.CALIB, pack_theta(D, o, dip))
    assert np.abs(f.unwhitenedError(v)).max() < 1e-12


def test_right_jacobian_numerical(rng):
    th = rng.normal(0, 0.8, 3)
    d = 1e-7
    Jn = np.stack([gtsam.Rot3.Logmap(gtsam.Rot3(expmap(th).T @ expmap(th + d * e))) / d for e in np.eye(3)], 1)
    np.testing.assert_allclose(right_jacobian(th), Jn, atol=1e-6)


def test_preintegration_matches_gtsam_and_bias_jacobian(rng):
    n, dt = 120, 0.01
    gyr = rng.normal(0, 1.0, (n, 3))
    bias = np.array([0.02, -0.01, 0.03])
    sig = np.array([0.01, 0.02, 0.015])
    kf, skf = keyframe_layout(n, 9)
    pre = preintegrate(gyr, np.full(n, dt), kf, skf, bias, sig)
    params = gtsam.PreintegratedRotationParams()
    params.setGyroscopeCovariance(np.diag(sig**2) * dt)
    for k in (0, 3, len(kf) - 2):
        pim = gtsam.PreintegratedAhrsMeasurements(params, bias)
        for i in range(kf[k], kf[k + 1]):
            pim.integrateMeasurement(gyr[i], dt)
        np.testing.assert_allclose(pre.delta_R[k], pim.deltaRij().matrix(), atol=1e-12)
        np.testing.assert_allclose(pre.cov[k], pim.preintMeasCov(), atol=1e-15)
    # the bias Jacobian, checked through AHRSFactor errors at a perturbed bias
    ours = ahrs_factors(pre, keys.rot, keys.BIAS, sig)[2]
    pim = gtsam.PreintegratedAhrsMeasurements(params, bias)
    for i in range(kf[2], kf[3]):
        pim.integrateMeasurement(gyr[i], dt)
    ref = gtsam.AHRSFactor(keys.rot(2), keys.rot(3), keys.BIAS, pim)
    v = gtsam.Values()
    v.insert(keys.rot(2), gtsam.Rot3.Expmap(rng.normal(0, 1, 3)))
    v.insert(keys.rot(3), gtsam.Rot3.Expmap(rng.normal(0, 1, 3)))
    v.insert(keys.BIAS, bias + np.array([0.01, -0.02, 0.005]))
    np.testing.assert_allclose(ours.unwhitenedError(v), ref.unwhitenedError(v), atol=1e-10)
    # intra-keyframe rotations: sample j of keyframe k is ΔR from s_k to j
    j = kf[4] + 5
    R = np.eye(3)
    for i in range(kf[4], j):
        R = R @ expmap((gyr[i] - bias) * dt)
    np.testing.assert_allclose(pre.kRb[j], R, atol=1e-12)
