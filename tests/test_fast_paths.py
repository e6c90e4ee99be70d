"""The vectorised fast paths of the calibration graph against plain reference computations written out
here: per-keyframe Gram sums, the chunked measurement linearisation, the padded preintegration, the
closed-form Exp / J_r pair, window-only sample orientations, and the solver's per-Values state cache."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.calibration.disturbance import Window
from imugraph.graphs.orientation_init import window_orientations
from imugraph.factors.gyro import exp_and_right_jacobian, keyframe_layout, preintegrate, right_jacobian
from imugraph.factors.magnetometer import magnetometer_model
from imugraph.factors.robust import Kernel
from imugraph.factors.theta import pack_theta
from imugraph.geometry import expmap, logmap, quat_to_rotmat
from imugraph.graphs import measurements, solver
from imugraph.graphs.measurements import ChannelData, MeasurementBlock, _gram_by
from imugraph.graphs.orientation_init import sample_orientations
from imugraph.graphs.solver import _damping, keyframe_rotations, optimize


@pytest.fixture
def rng():
    return np.random.default_rng(11)


def _naive_gram(index, X, n):
    out = np.zeros((n, X.shape[2], X.shape[2]))
    for j, b in enumerate(index):
        out[b] += X[j].T @ X[j]
    return out


@pytest.mark.parametrize("layout", ["regular", "short_last", "irregular", "unsorted", "empty_bins", "sparse"])
def test_gram_by_matches_loop(rng, layout):
    n, L = 9, 5
    counts = {"regular": np.full(n, L), "short_last": np.r_[np.full(n - 1, L), 2],
              "irregular": rng.integers(1, L + 1, n), "unsorted": rng.integers(1, L + 1, n),
              "empty_bins": np.r_[L, 0, L, 0, 3, L, 0, 1, L], "sparse": np.r_[np.zeros(n - 1, int), 40]}[layout]
    index = np.repeat(np.arange(n), counts)
    if layout == "unsorted":
        rng.shuffle(index)
    X = rng.normal(size=(len(index), 3, 6))
    np.testing.assert_allclose(_gram_by(index, X, n), _naive_gram(index, X, n), rtol=1e-12, atol=1e-12)


def _mag_block(rng, n=700, stride=23, thin=1):
    gyr = rng.normal(size=(n, 3)); dt = np.full(n, 0.01)
    kf, skf = keyframe_layout(n, stride)
    pre = preintegrate(gyr, dt, kf, skf, np.zeros(3), np.full(3, 0.01))
    y = rng.normal(size=(n, 3)) * 30.0
    keep = np.arange(n) % thin == 0
    ch = ChannelData(kf=skf[keep], kRb=pre.kRb[keep], values=y[keep], sigma=np.array([0.4, 0.5, 0.6]),
                     kernel=Kernel("huber", 1.0), weight_floor=rng.uniform(0.2, 1.0, keep.sum()))
    K = len(kf)
    nRk = quat_to_rotmat(rng.normal(size=(K, 4)))
    theta = pack_theta(np.eye(3) * 30 + rng.normal(size=(3, 3)), rng.normal(size=3), 0.9)
    return MeasurementBlock(K, None, ch, use_acc=False), nRk, theta


@pytest.mark.parametrize("thin", [1, 4])
def test_chunked_linearisation_matches_per_sample_jacobians(rng, thin, monkeypatch):
    block, nRk, theta = _mag_block(rng, thin=thin)
    ch = block.mag
    # reference: per-sample Jacobians of the (numerically tested) model, weighted and summed per keyframe
    e, J_rot, J_theta = magnetometer_model(ch.kRb, nRk[ch.kf], theta, ch.values)
    r = e / ch.sigma
    s = np.linalg.norm(r, axis=1)
    w = ch.kernel.weight(s) * ch.weight_floor
    A = np.concatenate([J_rot, J_theta], axis=2) / ch.sigma[None, :, None] * np.sqrt(w)[:, None, None]
    rw = r * np.sqrt(w)[:, None]
    H = np.zeros((block.n_keyframes, 16, 16)); g = np.zeros((block.n_keyframes, 16)); f = np.zeros(block.n_keyframes)
    for j, k in enumerate(ch.kf):
        H[k] += A[j].T @ A[j]; g[k] -= A[j].T @ rw[j]; f[k] += rw[j] @ rw[j]
    for chunk in (10**9, 50):
        monkeypatch.setattr(measurements, "CHUNK", chunk)
        G11, G12, G22, g1, g2, f_ = block.hessian_blocks(nRk, theta)
        scale = np.abs(H).max()
        np.testing.assert_allclose(G11, H[:, :3, :3], atol=1e-10 * scale)
        np.testing.assert_allclose(G12, H[:, :3, 3:], atol=1e-10 * scale)
        np.testing.assert_allclose(G22, H[:, 3:, 3:], atol=1e-10 * scale)
        np.testing.assert_allclose(g1, g[:, :3], atol=1e-10 * np.abs(g).max())
        np.testing.assert_allclose(g2, g[:, 3:], atol=1e-10 * np.abs(g).max())
        np.testing.assert_allclose(f_, f, rtol=1e-10)
    np.testing.assert_allclose(block.cost(nRk, theta), np.sum(ch.kernel.rho(s) * ch.weight_floor), rtol=1e-12)


def _preintegrate_loop(gyr, dt, kf_samples, bias, sigma, kappa):
    """Reference: the recursion of factors.gyro written sample by sample."""
    n = len(gyr)
    bounds = list(kf_samples) + [n]
    kRb = np.empty((n, 3, 3)); dRs, dbs, covs = [], [], []
    for a, b in zip(bounds[:-1], bounds[1:]):
        R, dRdb, cov = np.eye(3), np.zeros((3, 3)), np.zeros((3, 3))
        for j in range(a, b):
            kRb[j] = R
            w = gyr[j] - bias
            th = w * dt[j]
            inc = expmap(th)
            dRdb = inc.T @ dRdb - right_jacobian(th) * dt[j]
            cov = inc.T @ cov @ inc + np.diag((sigma**2 + kappa**2 * w @ w) * dt[j] ** 2)
            R = R @ inc
        dRs.append(R); dbs.append(dRdb); covs.append(cov)
    return kRb, np.array(dRs[:-1]), np.array(dbs[:-1]), np.array(covs[:-1])


def test_padded_preintegration_matches_sample_loop(rng):
    n = 311
    gyr = rng.normal(size=(n, 3)); dt = 0.01 + 0.001 * rng.random(n); bias = rng.normal(size=3) * 0.02
    kf, skf = keyframe_layout(n, 13)
    pre = preintegrate(gyr, dt, kf, skf, bias, np.array([0.01, 0.02, 0.015]), 0.01)
    kRb, dR, dRdb, cov = _preintegrate_loop(gyr, dt, kf, bias, np.array([0.01, 0.02, 0.015]), 0.01)
    np.testing.assert_allclose(pre.kRb, kRb, atol=1e-14)
    np.testing.assert_allclose(pre.delta_R, dR, atol=1e-14)
    np.testing.assert_allclose(pre.dR_db, dRdb, atol=1e-14)
    np.testing.assert_allclose(pre.cov, cov, rtol=1e-12, atol=1e-20)


def test_exp_and_right_jacobian(rng):
    th = rng.normal(size=(400, 3)) * np.logspace(-10, 0.4, 400)[:, None]
    R, J = exp_and_right_jacobian(th)
    np.testing.assert_allclose(R, expmap(th), atol=1e-15)
    np.testing.assert_allclose(J, right_jacobian(th), atol=1e-15)
    # J_r from its definition: Exp(θ + δ) ≈ Exp(θ) Exp(J_r δ)
    t, eps = np.array([0.3, -0.2, 0.5]), 1e-7
    cols = np.stack([logmap(expmap(t).T @ expmap(t + eps * e)) / eps for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(exp_and_right_jacobian(t)[1], cols, atol=1e-6)


def test_window_rotations_equal_whole_session_interpolation(rng):
    for n, stride in ((900, 57), (901, 50), (300, 7), (120, 120)):
        kf, skf = keyframe_layout(n, stride)
        pre = preintegrate(rng.normal(size=(n, 3)), np.full(n, 0.01), kf, skf, np.zeros(3), np.full(3, 0.01))
        nRk = quat_to_rotmat(rng.normal(size=(len(kf), 4)))
        full = quat_to_rotmat(sample_orientations(nRk, pre))
        windows = [Window(0, 10), Window(5, n), Window(n - 1, n), Window(stride - 1, min(stride + 1, n)),
                   Window(n // 3, n // 2)]
        got = window_orientations(windows, nRk, pre)
        for w in windows:
            np.testing.assert_array_equal(got[w.start:w.stop], full[w.start:w.stop])
        outside = np.ones(n, bool)
        for w in windows:
            outside[w.start:w.stop] = False
        assert np.all(np.isnan(got[outside]))


def test_state_cache_is_per_values_and_only_inside_optimize(rng, monkeypatch):
    values = gtsam.Values()
    R = quat_to_rotmat(rng.normal(size=(3, 4)))
    for k in range(3):
        values.insert(keys.rot(k), gtsam.Rot3(R[k]))
    a = keyframe_rotations(values, 3)
    values.update(keys.rot(1), gtsam.Rot3(R[0]))          # outside optimize: never cached
    np.testing.assert_allclose(keyframe_rotations(values, 3)[1], R[0], atol=1e-15)
    np.testing.assert_allclose(a[1], R[1], atol=1e-15)
    seen = []
    extract = solver._rotations
    monkeypatch.setattr(solver, "_rotations", lambda v, K: seen.append(v) or extract(v, K))

    class Block:                                       # reads the rotations in both cost and linearize
        def cost(self, v):
            keyframe_rotations(v, 3)
            return 0.0

        def linearize(self, v):
            keyframe_rotations(v, 3)
            return gtsam.GaussianFactorGraph()

    graph = gtsam.NonlinearFactorGraph()
    for k in range(3):
        graph.add(gtsam.PriorFactorRot3(keys.rot(k), gtsam.Rot3(R[k]), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    out, info = optimize(graph, [Block()], values, gtsam.Ordering([keys.rot(k) for k in range(3)]))
    assert len(seen) == len({id(v) for v in seen}) and len(seen) >= 2     # once per Values
    for k in range(3):
        np.testing.assert_allclose(out.atRot3(keys.rot(k)).matrix(), R[k], atol=1e-8)


def test_damping_reused_only_for_same_variables():
    kd = [(keys.rot(0), 3), (keys.vel(0), 6)]
    a = _damping(kd, 1e-3)
    assert _damping(list(kd), 1e-3) is a
    b = _damping([(keys.rot(0), 3)], 1e-3)
    assert b is not a and b.size() == 1
    H = _damping(kd, 1e-3).hessian(gtsam.Ordering([keys.rot(0), keys.vel(0)]))[0]
    np.testing.assert_allclose(H, 1e-3 * np.eye(9), atol=1e-18)
