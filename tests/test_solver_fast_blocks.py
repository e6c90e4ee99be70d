"""Fast paths of the calibration hot loop against their direct forms (computed here, independently):
per-sample interpolation as R_k·Exp(u·ε_k)·ΔR_j vs the slerp of forward and backward integration; the
linear field prior and gyro-map block as C++ LinearContainerFactors vs their Python linearisation; vector
extraction through gtsam.utilities.extractVectors vs key-by-key atVector."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.factors.field import field_key
from imugraph.factors.gyro import keyframe_layout, preintegrate
from imugraph.geometry import quat_mul, quat_conj, quat_slerp, quat_to_rotmat, rotmat_to_quat
from imugraph.graphs.field_block import FieldBlock
from imugraph.graphs.gyro_map_block import E_KEY, GyroMapBlock, beta_key
from imugraph.graphs.orientation_init import sample_orientations
from imugraph.graphs.solver import keyframe_vectors, optimize


@pytest.fixture
def rng():
    return np.random.default_rng(11)


def _slerp_reference(nRk, pre):
    """The direct definition: slerp(R_k ΔR_{k,j}, R_{k+1} ΔR_kᵀ ΔR_{k,j}, u_j), u_j = position in the interval."""
    out = np.zeros((len(pre.sample_kf), 4))
    K = len(nRk)
    for j, k in enumerate(pre.sample_kf):
        fwd = nRk[k] @ pre.kRb[j]
        if k == K - 1:
            out[j] = rotmat_to_quat(fwd)
            continue
        bwd = nRk[k + 1] @ pre.delta_R[k].T @ pre.kRb[j]
        u = (j - pre.kf_samples[k]) / (pre.kf_samples[k + 1] - pre.kf_samples[k])
        out[j] = quat_slerp(rotmat_to_quat(fwd), rotmat_to_quat(bwd), np.array(u))
    return out


def _angle(qa, qb):
    rel = quat_mul(quat_conj(qa / np.linalg.norm(qa, axis=1, keepdims=True)),
                   qb / np.linalg.norm(qb, axis=1, keepdims=True))
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(rel[:, 1:], axis=1), 0.0, 1.0))


@pytest.mark.parametrize("n, stride, spread", [(400, 37, 0.05), (301, 50, 1.0), (120, 120, 0.3), (50, 7, 2.5)])
def test_sample_orientations_equal_slerp_of_forward_and_backward(rng, n, stride, spread):
    """spread: how far the keyframe rotations are from the gyro's (2.5 rad: closing errors near π)."""
    kf, skf = keyframe_layout(n, stride)
    pre = preintegrate(rng.normal(size=(n, 3)), np.full(n, 0.01), kf, skf, np.zeros(3), np.full(3, 0.01))
    nRk = np.empty((len(kf), 3, 3))
    nRk[0] = quat_to_rotmat(rng.normal(size=4))
    for k in range(1, len(kf)):          # the gyro's chain, perturbed by up to `spread` rad per keyframe
        w = rng.normal(size=3)
        w *= spread * rng.uniform() / np.linalg.norm(w)
        nRk[k] = nRk[k - 1] @ pre.delta_R[k - 1] @ quat_to_rotmat(np.r_[np.cos(np.linalg.norm(w) / 2),
                                                                       np.sin(np.linalg.norm(w) / 2) * w / np.linalg.norm(w)])
    got, want = sample_orientations(nRk, pre), _slerp_reference(nRk, pre)
    assert got.shape == (n, 4)
    assert np.max(_angle(got, want)) < 1e-12


def test_sample_orientations_single_keyframe(rng):
    kf, skf = keyframe_layout(5, 10)
    kf, skf = kf[:1], np.zeros(5, int)
    pre = preintegrate(rng.normal(size=(5, 3)), np.full(5, 0.01), kf, skf, np.zeros(3), np.full(3, 0.01))
    R0 = quat_to_rotmat(rng.normal(size=4))
    got = quat_to_rotmat(sample_orientations(R0[None], pre))
    np.testing.assert_allclose(got, R0 @ pre.kRb, atol=1e-14)


def _same_linearisation(nl_graph, gfg_direct, values, order):
    """The C++ graph's linearisation and error at `values` equal the direct Jacobians' (augmented Hessian)."""
    H_cpp = nl_graph.linearize(values).augmentedHessian(gtsam.Ordering(order))
    H_dir = gfg_direct.augmentedHessian(gtsam.Ordering(order))
    scale = np.abs(H_dir).max()
    np.testing.assert_allclose(H_cpp, H_dir, rtol=1e-12, atol=1e-12 * scale)


@pytest.mark.parametrize("sigma", [0.02, (0.015, 0.003, 0.015)])
def test_field_prior_factors_equal_python_linearisation(rng, sigma):
    K = 7
    blk = FieldBlock(rng.uniform(0.1, 0.3, K - 1), sigma, 1.2)
    nl = blk.factors()
    for _ in range(2):
        vals = gtsam.Values()
        for k in range(K):
            vals.insert(field_key(k), 0.03 * rng.normal(size=3))
        _same_linearisation(nl, blk.linearize(vals), vals, [field_key(k) for k in range(K)])
        assert np.isclose(nl.error(vals), blk.cost(vals), rtol=1e-12)


def test_gyro_map_factors_equal_python_linearisation(rng):
    n, seg = 6, np.array([0, 0, 1, 1, 1, 2])
    blk = GyroMapBlock(rng.normal(scale=0.5, size=(n, 3, 9)), seg, keys.bias, 0.01 * rng.normal(size=9), 0.02)
    nl = blk.factors()
    vals = gtsam.Values()
    for k in range(n):
        vals.insert(beta_key(k), 0.01 * rng.normal(size=3))
    for i in range(3):
        vals.insert(keys.bias(i), 0.01 * rng.normal(size=3))
    vals.insert(E_KEY, 0.003 * rng.normal(size=9))
    order = [beta_key(k) for k in range(n)] + [keys.bias(i) for i in range(3)] + [E_KEY]
    _same_linearisation(nl, blk.linearize(vals), vals, order)
    assert np.isclose(nl.error(vals), blk.cost(vals), rtol=1e-10)


def test_keyframe_vectors_fast_and_fallback_paths(rng):
    K = 5
    v = gtsam.Values()
    d = rng.normal(size=(K, 3))
    for k in range(K):
        v.insert(field_key(k), d[k])
        v.insert(keys.rot(k), gtsam.Rot3())
    v.insert(keys.vel(0), np.ones(3))
    np.testing.assert_array_equal(keyframe_vectors(v, field_key, K), d)        # extract + extractVectors path
    np.testing.assert_array_equal(keyframe_vectors(v, field_key, 3), d[:3])    # more f keys than asked
    v.insert(gtsam.symbol("f", 9), np.zeros(3))                                # another f key beyond K
    np.testing.assert_array_equal(keyframe_vectors(v, field_key, K), d)
    np.testing.assert_array_equal(keyframe_vectors(v, lambda k: field_key(2 * k), 3), d[[0, 2, 4]])  # key by key
    v.erase(field_key(2))
    with pytest.raises(RuntimeError):                                          # a missing key raises, as atVector
        keyframe_vectors(v, field_key, K)


def test_optimize_with_linear_container_prior_matches_python_block(rng):
    """LM on the field prior plus a measurement-like prior: the same solution with the prior as C++
    LinearContainerFactors in the graph as with FieldBlock in the solver's block list."""
    K = 6
    blk = FieldBlock(rng.uniform(0.1, 0.3, K - 1), (0.02, 0.01, 0.03), 1.0)
    meas = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    for k in range(K):
        meas.add(gtsam.PriorFactorVector(field_key(k), 0.05 * rng.normal(size=3), gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
        vals.insert(field_key(k), np.zeros(3))
    order = gtsam.Ordering([field_key(k) for k in range(K)])
    with_block, _ = optimize(meas, [blk], vals, order)
    g2 = gtsam.NonlinearFactorGraph(meas)
    g2.push_back(blk.factors())
    with_cpp, _ = optimize(g2, [], vals, order)
    for k in range(K):
        np.testing.assert_allclose(with_cpp.atVector(field_key(k)), with_block.atVector(field_key(k)), atol=1e-12)


@pytest.mark.parametrize("n, stride", [(260, 40), (261, 40), (300, 7)])
def test_map_jacobian_from_kept_steps_equals_recomputed(rng, n, stride):
    """calibration.gyro_map.map_jacobian from preintegrate's kept kRb_j Exp(θ_j) J_r(θ_j)Δt_j (regular and
    irregular layouts) equals the recomputation; the preintegration itself is unchanged by keep_steps."""
    from imugraph.calibration.gyro_map import map_jacobian
    from imugraph.factors.gyro import exp_and_right_jacobian

    g = rng.normal(scale=1.5, size=(n, 3))
    dt = np.full(n, 1 / 200) * rng.uniform(0.9, 1.1, n)
    kf, skf = keyframe_layout(n, stride)
    b = np.tile([0.02, -0.03, 0.01], (n, 1))
    plain = preintegrate(g, dt, kf, skf, b, np.full(3, 1e-3), 0.01)
    kept = preintegrate(g, dt, kf, skf, b, np.full(3, 1e-3), 0.01, keep_steps=True)
    np.testing.assert_array_equal(kept.kRb, plain.kRb)
    np.testing.assert_array_equal(kept.delta_R, plain.delta_R)
    exp, jr = exp_and_right_jacobian((g - b) * dt[:, None])
    np.testing.assert_allclose(kept.steps, plain.kRb @ exp @ jr * dt[:, None, None], atol=1e-15)
    A, B = map_jacobian(g, dt, kept, b), map_jacobian(g, dt, plain, b)
    np.testing.assert_allclose(A, B, rtol=1e-12, atol=1e-14 * np.abs(B).max())
