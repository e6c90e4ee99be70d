"""The speed changes of issue 2e against the paths they replace, which are written out or kept here:
sequential vs multifrontal elimination of the same linear system, the AR(2) velocity terms as C++
LinearContainerFactors in the graph vs the Python-built factors per iteration (same normal equations and
cost, and the zero Gauss–Markov rows left out change nothing), the cached field prior, and a whole
calibration solved both ways."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.factors.field import field_key
from imugraph.factors.gyro import keyframe_layout, preintegrate
from imugraph.geometry import quat_to_rotmat
from imugraph.graphs import field_block
from imugraph.graphs.field_block import FieldBlock
from imugraph.graphs.single_imu import Noise, VelocityModel, build_problem
from imugraph.graphs.solver import SolverParams, _solve, optimize, state_keys
from imugraph.graphs.velocity_block import VelocityBlock


@pytest.fixture
def rng():
    return np.random.default_rng(5)


def _velocity_problem(rng, K=12, ar2=(1.4, -0.6, 0.04), acc_bias=False):
    """A VelocityBlock with random increments and a Values holding random R_k and s_k."""
    d = 6 if acc_bias else 3
    B = rng.normal(size=(K - 1, 3, 3)) * 0.1 if acc_bias else None
    vb = VelocityBlock(rng.normal(size=(K - 1, 3)), rng.uniform(0.05, 0.2, K - 1), np.full(K - 1, 0.2), 9.81,
                       B=B, ar2=ar2)
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(quat_to_rotmat(rng.normal(size=4))))
        values.insert(keys.vel(k), rng.normal(size=d))
    return vb, values


def _normal_equations(gfg: gtsam.GaussianFactorGraph, order: list) -> np.ndarray:
    return gfg.augmentedHessian(gtsam.Ordering(order))


@pytest.mark.parametrize("acc_bias", [False, True])
def test_ar2_in_graph_same_normal_equations_and_cost(rng, acc_bias):
    vb, values = _velocity_problem(rng, acc_bias=acc_bias)
    K = vb.n_keyframes
    order = list(state_keys(keys.rot, K)) + list(state_keys(keys.vel, K))
    # reference: every term built in Python at the linearisation point (the AR(2) factors included)
    ref = _normal_equations(vb.linearize(values), order)
    ref_cost = vb.cost(values)
    lcf = vb.ar2_graph()
    vb.ar2_in_graph = True
    gfg = vb.linearize(values)
    gfg.push_back(lcf.linearize(values))
    np.testing.assert_allclose(_normal_equations(gfg, order), ref, rtol=1e-10, atol=1e-9)
    assert vb.cost(values) + lcf.error(values) == pytest.approx(ref_cost, rel=1e-12)
    assert vb.cost(values) < ref_cost            # the AR(2) part really left the Python cost


def test_velocity_normal_equations_are_the_cost_derivatives(rng):
    """With the orientations held the block's cost (cost_at, AR(2) terms included: a separate numpy formula)
    is quadratic in the velocities: its finite-difference gradient and Hessian must equal the normal equations
    of the factors actually built (interval factors without the zero rows, AR(2) terms from the graph)."""
    vb, values = _velocity_problem(rng, K=8)
    K, d = vb.n_keyframes, vb.state_dim
    nRk = np.array([values.atRot3(keys.rot(k)).matrix() for k in range(K)])
    s0 = np.array([values.atVector(keys.vel(k)) for k in range(K)])
    lcf = vb.ar2_graph()
    vb.ar2_in_graph = True
    gfg = vb.linearize(values)
    gfg.push_back(lcf.linearize(values))
    M = _normal_equations(gfg, list(state_keys(keys.vel, K)) + list(state_keys(keys.rot, K)))
    n = K * d
    H, g = M[:n, :n], -M[:n, -1]              # ½|Aδ − b|²: Hessian AᵀA, gradient −Aᵀb at δ = 0

    def f(x):
        return vb.cost_at(nRk, x.reshape(K, d), with_ar2=True)

    h, x0 = 1e-3, s0.ravel()
    E = np.eye(n) * h
    grad = np.array([(f(x0 + E[i]) - f(x0 - E[i])) / (2 * h) for i in range(n)])
    hess = np.array([[(f(x0 + E[i] + E[j]) - f(x0 + E[i] - E[j]) - f(x0 - E[i] + E[j]) + f(x0 - E[i] - E[j]))
                      / (4 * h * h) for j in range(n)] for i in range(n)])
    np.testing.assert_allclose(grad, g, rtol=1e-6, atol=1e-6 * np.abs(g).max())
    np.testing.assert_allclose(hess, H, rtol=1e-5, atol=1e-5 * np.abs(H).max())


def test_ar2_terms_written_out(rng):
    """The graph's AR(2) factors against the formula: ½ Σ_k |v_{k+1} − a_1 v_k − a_2 v_{k−1}|² / q."""
    a1, a2, q = 1.3, -0.5, 0.02
    vb, values = _velocity_problem(rng, K=9, ar2=(a1, a2, q))
    v = np.array([values.atVector(keys.vel(k)) for k in range(9)])
    expected = 0.5 * sum(np.sum((v[k + 1] - a1 * v[k] - a2 * v[k - 1]) ** 2) / q for k in range(1, 8))
    assert vb.ar2_graph().error(values) == pytest.approx(expected, rel=1e-12)


def test_sequential_and_multifrontal_agree(rng):
    vb, values = _velocity_problem(rng, ar2=None)
    K = vb.n_keyframes
    gfg = vb.linearize(values)
    for k in range(K):                       # make every variable determined
        gfg.push_back(gtsam.JacobianFactor(keys.rot(k), np.eye(3), np.zeros(3), gtsam.noiseModel.Unit.Create(3)))
    ordering = gtsam.Ordering([key for k in range(K) for key in (keys.rot(k), keys.vel(k))])
    d_seq, d_mf = _solve(gfg, ordering, "sequential"), _solve(gfg, ordering, "multifrontal")
    for k in range(K):
        for key in (keys.rot(k), keys.vel(k)):
            np.testing.assert_allclose(d_seq.at(key), d_mf.at(key), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="elimination"):
        _solve(gfg, ordering, "qr")


def test_field_prior_cached_only_for_same_settings():
    dt = np.full(20, 0.2)
    g1 = FieldBlock(dt, (0.015, 0.003, 0.015), 1.0).factors()
    assert FieldBlock(dt.copy(), (0.015, 0.003, 0.015), 1.0).factors() is g1
    g2 = FieldBlock(dt, (0.015, 0.003, 0.015), 2.0).factors()
    assert g2 is not g1
    zero = gtsam.Values()
    for key in state_keys(field_key, 21):
        zero.insert(key, np.full(3, 0.01))
    fresh = FieldBlock(dt, (0.015, 0.003, 0.015), 2.0)._linear_container()
    assert g2.error(zero) == pytest.approx(fresh.error(zero), rel=1e-14)
    field_block._LAST_FACTORS.clear()


def _calibration_problem(rng, n=1500, stride=25):
    t = np.arange(n) * 0.01
    gyr = np.c_[np.sin(t), np.cos(0.7 * t), 0.5 * np.sin(0.3 * t)] + rng.normal(size=(n, 3)) * 0.01
    dt = np.full(n, 0.01)
    kf, skf = keyframe_layout(n, stride)
    pre = preintegrate(gyr, dt, kf, skf, np.zeros(3), np.full(3, 0.01))
    K = len(kf)
    acc = rng.normal(size=(n, 3)) * 0.3 + [0, 0, 9.81]
    mag = rng.normal(size=(n, 3)) * 0.05 + [0.5, 0.0, -0.8]
    noise = Noise(np.full(3, 0.01), np.full(3, 0.3), np.full(3, 0.05))
    nRk0 = np.tile(np.eye(3), (K, 1, 1))
    theta0 = np.r_[np.eye(3).ravel(), np.zeros(3), 0.9]
    return build_problem(pre, acc, mag, noise, 9.81, nRk0, np.zeros(3), theta0, dt=dt,
                         velocity=VelocityModel(ar2=(1.4, -0.6, 0.04), acc_bias=False))


def test_whole_solve_same_either_elimination(rng):
    prob = _calibration_problem(rng)
    out = {}
    for how in ("sequential", "multifrontal"):
        out[how], info = optimize(prob.graph, prob.blocks, prob.values, prob.ordering,
                                  SolverParams(max_iterations=20, elimination=how))
        assert info.iterations > 1
    np.testing.assert_allclose(out["sequential"].atVector(keys.CALIB), out["multifrontal"].atVector(keys.CALIB),
                               rtol=1e-8, atol=1e-10)
