"""Velocity-process variants of H9 (issue 2c): the inverse-gamma prior on the AR(2) innovation variance
("map_ar2", calibration/velocity_ar2.py) and the motion-intensity (heteroscedastic) process ("hetero_ar2",
calibration/velocity_hetero.py), with the graph-side patch it needs (benchmarks/h9_hetero_patch.py).
Expected values come from independent formulas (least squares on the moments, dense matrices, direct loops)."""

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.calibration.velocity_ar2 import fit_ar2
from imugraph.calibration.velocity_hetero import (HeteroQ, fit_hetero, interval_intensity, scale_for,
                                                  update_hetero, weighted_terms)
from imugraph.calibration.velocity_process import chain_bands, process_bounds
from imugraph.factors.velocity import ar2_residuals
from imugraph.geometry import expmap
from imugraph.graphs.velocity_block import VelocityBlock

FREE = ((0.01, 5.0), np.exp(-0.2 / 30.0))


def _moments(v: np.ndarray):
    """Exact (P = 0) lag moments summed over axes of a realisation v (K, n), as velocity_ar2.lag_moments."""
    K = len(v)
    return [np.sum(v[:K - l] * v[l:], axis=1) for l in range(3)]


def _simulate(rng, a1, a2, q, K, h=None, n=3):
    v = np.zeros((K, n))
    h = np.ones(K - 2) if h is None else h
    for m in range(K - 2):
        v[m + 2] = a1 * v[m + 1] + a2 * v[m] + rng.normal(scale=np.sqrt(q * h[m]), size=n)
    return v


def test_map_prior_leaves_a_and_shrinks_q_to_the_conjugate_mode():
    rng = np.random.default_rng(3)
    v = _simulate(rng, 0.6, 0.05, 0.001, 3000)
    E = _moments(v)
    terms = weighted_terms(E, np.ones(len(v) - 2))
    N = 3 * (len(v) - 2)
    a_ml = fit_ar2(*terms, N, *FREE)
    q0, nu0 = 0.045, 300.0
    a_map = fit_ar2(*terms, N, *FREE, prior=(q0, nu0))
    assert a_map[:2] == pytest.approx(a_ml[:2], abs=1e-12)          # a prior on q alone does not move a
    # f(a) by least squares on the stacked regression, independent of the moment algebra under test
    y, X = v[2:].ravel(), np.stack([v[1:-1].ravel(), v[:-2].ravel()], axis=1)
    f = float(np.sum((y - X @ np.array(a_map[:2])) ** 2))
    assert a_map[2] == pytest.approx((f + nu0 * q0) / (N + nu0), rel=1e-9)
    assert a_ml[2] == pytest.approx(f / N, rel=1e-2)                 # ML at its own (grid) a
    assert fit_ar2(*terms, N, *FREE, prior=(q0, 1e9))[2] == pytest.approx(q0, rel=1e-4)


def test_map_mode_is_free_of_bounds_and_named_in_the_error():
    assert process_bounds("map_ar2", 0.5, 2.0) == process_bounds("free_ar2", 0.5, 2.0)
    with pytest.raises(ValueError, match="estimate_velocity_process.*map_ar2"):
        process_bounds("mapp", 0.5, 2.0)


def test_interval_intensity_is_the_mean_deviation_per_interval():
    rng = np.random.default_rng(0)
    acc = rng.normal(size=(23, 3)) + [0, 0, 9.8]
    skf = np.repeat(np.arange(5), [5, 5, 5, 5, 3])
    u = interval_intensity(acc, 9.8, skf, 5)
    expect = [np.mean([abs(np.linalg.norm(acc[j]) - 9.8) for j in range(23) if skf[j] == k]) for k in range(4)]
    np.testing.assert_allclose(u, expect, rtol=1e-12)


def test_weighted_m_step_recovers_the_intensity_weight():
    rng = np.random.default_rng(5)
    K, lam = 20000, 3.0
    u = rng.gamma(0.5, 2.0, size=K - 1)
    h = scale_for(u, lam)
    v = _simulate(rng, 0.5, 0.2, 0.002, K, h)
    a1, a2, q, lam_e, _ = fit_hetero(_moments(v), u, 3 * (K - 2), *FREE)
    assert 1.0 <= lam_e <= 10.0                                      # the grid steps ×2.15
    assert abs(a1 - 0.5) < 0.03 and abs(a2 - 0.2) < 0.03
    v0 = _simulate(rng, 0.5, 0.2, 0.002, K)                          # stationary data: λ stays near 0
    assert fit_hetero(_moments(v0), u, 3 * (K - 2), *FREE)[3] <= 0.1


def _block(rng, K, q):
    dv = rng.normal(size=(K - 1, 3))
    return VelocityBlock(dv, np.full(K - 1, 0.05), np.full(K - 1, 0.2), 9.81, ar2=(0.4, 0.3, q))


def _ar2_dense(K, a1, a2, q, h):
    """Dense precision of the AR(2) innovation rows m = 0 … K−3 (without the stationary start)."""
    J = np.zeros((K - 2, K))
    for m in range(K - 2):
        J[m, m:m + 3] = np.array([-a2, -a1, 1.0]) / np.sqrt(q * h[m])
    return J.T @ J


def test_chain_bands_scale_each_innovation_by_h():
    rng = np.random.default_rng(2)
    K, q = 9, 0.01
    h = rng.uniform(0.5, 4.0, size=K - 2)
    nRk, s = expmap(rng.normal(size=(K, 3))), rng.normal(size=(K, 3))
    plain = chain_bands(_block(rng, K, q), nRk, s)
    rng = np.random.default_rng(2)
    hetero = chain_bands(_block(rng, K, HeteroQ(q, h)), expmap(rng.normal(size=(K, 3))), s)
    diff = _ar2_dense(K, 0.4, 0.3, q, h) - _ar2_dense(K, 0.4, 0.3, q, np.ones(K - 2))
    for l in range(3):
        np.testing.assert_allclose(hetero[l, :K - l] - plain[l, :K - l],
                                   np.repeat(np.diag(diff, -l)[:, None], 3, axis=1), atol=1e-9)


def test_hetero_refuses_a_graph_without_the_patch(monkeypatch):
    import imugraph.factors.velocity as fv
    from benchmarks import h9_hetero_patch as patch

    monkeypatch.setattr(fv, "ar2_residuals", patch._plain_residuals)
    state = {"s": np.zeros((6, 3)), "sigma": 0.5, "tau": 2.0, "ar2": None, "intensity": np.ones(5)}
    block = VelocityBlock(np.zeros((5, 3)), np.full(5, 0.1), np.full(5, 0.2), 9.81)
    with pytest.raises(NotImplementedError, match="hetero_ar2"):
        update_hetero(state, block, np.tile(np.eye(3), (6, 1, 1)), None, (0.01, 5.0), (0.05, 30.0))


def test_patched_ar2_factors_are_the_scaled_residuals(monkeypatch):
    from benchmarks import h9_hetero_patch as patch
    import imugraph.graphs.velocity_block as vbm

    monkeypatch.setattr(vbm, "ar2_residuals", patch.ar2_residuals)
    monkeypatch.setattr(vbm.VelocityBlock, "_ar2_factors", patch._ar2_factors)
    rng = np.random.default_rng(4)
    K, q = 7, 0.02
    h = rng.uniform(0.5, 4.0, size=K - 2)
    block = _block(rng, K, HeteroQ(q, h))
    s = rng.normal(size=(K, 3))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.vel(k), s[k])
    gfg = gtsam.GaussianFactorGraph()
    block._ar2_factors(gfg, s, [keys.vel(k) for k in range(K)])
    zero = gtsam.VectorValues()
    for k in range(K):
        zero.insert(keys.vel(k), np.zeros(3))
    # at δ = 0 the linear factors' error is ½ Σ of the whitened innovations, computed here directly
    e = (s[2:] - 0.4 * s[1:-1] - 0.3 * s[:-2]) / np.sqrt(q * h)[:, None]
    assert gfg.error(zero) == pytest.approx(0.5 * np.sum(e**2), rel=1e-12)
    np.testing.assert_allclose(patch.ar2_residuals(s, 0.4, 0.3, HeteroQ(q, h))[2:], e, rtol=1e-12)
    np.testing.assert_allclose(patch.ar2_residuals(s, 0.4, 0.3, q), ar2_residuals(s, 0.4, 0.3, q), rtol=0)


def test_capped_mode_bounds_only_the_correlation_time():
    from imugraph.calibration.velocity_process import SIGMA_BOUNDS

    assert process_bounds("capped_ar2", 0.5, 2.0) == (SIGMA_BOUNDS, (0.05, 2.0))
    # moments of a small, slowly drifting process (the free estimate on BROAD 01/04/06: a slow real root ≈ 0.97)
    # plus its small steps: capped keeps the slow root ≤ φ_max but lets q fall below the bounded floor
    rng = np.random.default_rng(8)
    v = _simulate(rng, 0.68, 0.30, 0.0015, 20000)
    E = _moments(v)
    terms = weighted_terms(E, np.ones(len(v) - 2))
    N = 3 * (len(v) - 2)
    phi_max = np.exp(-0.2 / 2.0)
    b1, b2, qb = fit_ar2(*terms, N, SIGMA_BOUNDS, phi_max)
    disc = b1**2 + 4 * b2
    assert disc < 0 or (b1 + np.sqrt(disc)) / 2 <= phi_max + 1e-12
    assert b1 / (1 - b2) <= phi_max + 1e-12
    assert qb < 0.5**2 * (1 - phi_max**2) / 10          # the "bounded" floor would be 0.045 (m/s)²
