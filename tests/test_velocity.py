"""The velocity-increment factor (imugraph.factors.velocity): Jacobians against numerical derivatives,
the block's linearisation against its own cost, and the physics it encodes on simulated motion."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.factors.gyro import keyframe_layout, preintegrate
from imugraph.factors.velocity import gauss_markov, gauss_markov_axes, velocity_increments, velocity_model
from imugraph.geometry import expmap
from imugraph.graphs.velocity_block import VelocityBlock
from imugraph.factors.robust import Kernel


def _random_state(rng, K):
    nRk = expmap(rng.normal(size=(K, 3)))
    v = rng.normal(scale=0.5, size=(K, 3))
    dv = rng.normal(scale=1.0, size=(K - 1, 3))
    dt_k = np.full(K - 1, 0.1)
    return nRk, v, dv, dt_k


def test_velocity_jacobian_rotation_matches_numerical():
    rng = np.random.default_rng(3)
    nRk, v, dv, dt_k = _random_state(rng, 6)
    _, J_R = velocity_model(nRk, v, dv, dt_k, 9.81)
    h = 1e-6
    for i in range(3):
        d = np.zeros(3); d[i] = h
        plus = nRk @ expmap(np.broadcast_to(d, (6, 3)))
        minus = nRk @ expmap(np.broadcast_to(-d, (6, 3)))
        e_p, _ = velocity_model(plus, v, dv, dt_k, 9.81)
        e_m, _ = velocity_model(minus, v, dv, dt_k, 9.81)
        np.testing.assert_allclose((e_p - e_m) / (2 * h), J_R[:, :, i], atol=1e-7)


def test_velocity_residual_zero_for_consistent_motion():
    # constant nav-frame acceleration a_n with a fixed attitude: v_{k+1} = v_k + a_n Δt exactly
    rng = np.random.default_rng(4)
    K, g = 5, 9.81
    R = expmap(rng.normal(size=3))
    a_n = np.array([0.3, -0.2, 0.5])
    f_b = R.T @ (a_n - np.array([0.0, 0.0, -g]))       # specific force in the body frame
    dt_k = np.full(K - 1, 0.1)
    v = np.cumsum(np.vstack([np.zeros(3), np.tile(a_n * 0.1, (K - 1, 1))]), axis=0)
    e, _ = velocity_model(np.tile(R, (K, 1, 1)), v, np.tile(f_b * 0.1, (K - 1, 1)), dt_k, g)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)


@pytest.mark.parametrize("with_bias", [False, True])
@pytest.mark.parametrize("with_rest", [False, True])
@pytest.mark.parametrize("per_axis", [False, True])
def test_block_linearisation_is_gradient_of_cost(with_bias, with_rest, per_axis, assert_block_gradient):
    rng = np.random.default_rng(5)
    K = 7
    nRk, v, dv, dt_k = _random_state(rng, K)
    B = expmap(rng.normal(size=(K - 1, 3))) * 0.1 if with_bias else None
    sigma_v, tau_v = (np.array([0.7, 0.7, 1.2]), np.array([1.5, 1.5, 0.4])) if per_axis else (0.7, 1.5)
    block = VelocityBlock(dv, np.full(K - 1, 0.05), dt_k, 9.81, sigma_v=sigma_v, tau_v=tau_v,
                          kernel=Kernel("huber", 2.0), B=B, bias_sigma0=0.2, bias_rw=0.01,
                          rest=np.array([True, True, False, False, False, True, False]) if with_rest else None)
    if with_bias:
        v = np.hstack([v, rng.normal(scale=0.1, size=(K, 3))])
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk[k]))
        values.insert(keys.vel(k), v[k])
    key_list = [keys.rot(k) for k in range(K - 1)] + [keys.vel(k) for k in range(K)]  # R_{K-1}: no interval
    assert_block_gradient(block, values, key_list)


def test_gauss_markov_is_stationary():
    # variance stays σ_v² along the chain: φ² σ_v² + σ_w² = σ_v²
    phi, sigma_w = gauss_markov(np.array([0.01, 0.1, 1.0, 10.0]), 0.5, 2.0)
    np.testing.assert_allclose(phi**2 * 0.25 + sigma_w**2, 0.25)


def test_increments_integrate_simulated_specific_force():
    from imugraph.sim.motion import random_rotation_motion
    from imugraph.sim.sensors import SensorParams, simulate_imu
    from imugraph.geometry import quat_to_rotmat

    rng = np.random.default_rng(2)
    motion = random_rotation_motion(20.0, 200.0, rng, translation_m=0.2)
    params = SensorParams()
    sens = simulate_imu(motion.t, motion.nRb, motion.b_omega, motion.n_acc, params, rng)
    gyr, acc = sens.gyr, sens.acc
    dt = np.diff(motion.t, append=motion.t[-1] + (motion.t[1] - motion.t[0]))
    kf, skf = keyframe_layout(len(motion.t), 20)
    pre = preintegrate(gyr, dt, kf, skf, np.zeros(3), np.full(3, 1e-4))
    dv, sig = velocity_increments(pre.kRb, skf, acc, dt, len(kf), np.full(3, 1e-3), 0.0)
    nRk = quat_to_rotmat(motion.nRb[kf])
    # true velocity: integral of the true nav-frame linear acceleration
    n_v = np.vstack([np.zeros(3), np.cumsum(motion.n_acc[:-1] * dt[:-1, None], axis=0)])
    e, _ = velocity_model(nRk, n_v[kf], dv, pre.dt, params.g)
    assert np.max(np.abs(e)) < 0.02 * max(1.0, np.max(np.abs(n_v)))
    assert np.all(sig > 0)


def test_heading_block_linearisation_is_gradient_along_the_vertical():
    """The heading factor informs the rotation about the navigation vertical only: its linearisation
    matches the cost's derivative for yaw perturbations and holds no information on tilt."""
    from imugraph.graphs.heading_block import HeadingBlock

    rng = np.random.default_rng(8)
    K, M = 4, 40
    nRk = expmap(rng.normal(size=(K, 3)))
    kf = np.sort(rng.integers(0, K, M))
    kRb = expmap(0.1 * rng.normal(size=(M, 3)))
    m = rng.normal(size=(M, 3))
    block = HeadingBlock(kf, kRb, m, 0.02, K, Kernel("huber", 2.0))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk[k]))
    key_list = [keys.rot(k) for k in range(K)]
    H = block.linearize(values).augmentedHessian(gtsam.Ordering(key_list))
    grad, G = -H[:-1, -1], H[:-1, :-1]
    h = 1e-6
    for k, key in enumerate(key_list):
        yaw = nRk[k].T @ np.array([0.0, 0.0, 1.0])      # body-frame axis of a nav-vertical rotation
        p, q = gtsam.Values(values), gtsam.Values(values)
        p.update(key, values.atRot3(key).retract(h * yaw)); q.update(key, values.atRot3(key).retract(-h * yaw))
        numerical = (block.cost(p) - block.cost(q)) / (2 * h)
        np.testing.assert_allclose(grad[3 * k:3 * k + 3] @ yaw, numerical, rtol=1e-5, atol=1e-6)
        Gk = G[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        tilt = np.cross(yaw, rng.normal(size=3))        # a rotation about a horizontal nav axis
        assert abs(tilt @ Gk @ tilt) < 1e-9 * np.trace(Gk) and abs(grad[3 * k:3 * k + 3] @ tilt) < 1e-9


def test_gauss_markov_axes_is_the_scalar_chain_per_axis():
    dt_k = np.array([0.05, 0.2, 1.0])
    phi, sig_w = gauss_markov_axes(dt_k, np.array([0.5, 0.5, 1.1]), np.array([2.0, 2.0, 0.3]))
    for axis, (s, t) in enumerate([(0.5, 2.0), (0.5, 2.0), (1.1, 0.3)]):
        p1, w1 = gauss_markov(dt_k, s, t)
        np.testing.assert_allclose(phi[:, axis], p1, rtol=1e-14)
        np.testing.assert_allclose(sig_w[:, axis], w1, rtol=1e-14)
    p_iso, w_iso = gauss_markov_axes(dt_k, 0.5, 2.0)
    np.testing.assert_allclose(p_iso, np.repeat(gauss_markov(dt_k, 0.5, 2.0)[0][:, None], 3, axis=1))
