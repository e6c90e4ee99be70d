"""The gyro's rate-proportional noise κ re-estimated from the gyro factors (imugraph.calibration.gyro_rate)."""

from __future__ import annotations

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.calibration.gyro_rate import estimate_rate_variance, rate_energy, update_rate_error
from imugraph.factors.gyro import ahrs_factors, keyframe_layout, preintegrate
from imugraph.geometry import expmap


def _rates(n: int, dt: float, rng) -> np.ndarray:
    """Smooth rates of a few rad/s about all axes (sums of sines with random phases)."""
    t = np.arange(n) * dt
    f = rng.uniform(0.2, 1.5, (3, 3))
    ph = rng.uniform(0, 2 * np.pi, (3, 3))
    return np.stack([sum(1.2 * np.sin(2 * np.pi * f[a, i] * t + ph[a, i]) for i in range(3)) for a in range(3)], 1)


def test_rate_energy_matches_direct_sum():
    """B_k from the preintegrated rotations equals Σ_j |ω_j − b|² Δt_j² computed from the rates."""
    rng = np.random.default_rng(3)
    n, dt = 203, np.full(203, 0.01)
    w = _rates(n, 0.01, rng)
    b = np.array([0.01, -0.02, 0.03])
    kf, skf = keyframe_layout(n, 20)
    pre = preintegrate(w, dt, kf, skf, b, np.full(3, 1e-3))
    direct = np.array([np.sum(((w[kf[k]:kf[k + 1]] - b) * 0.01) ** 2) for k in range(len(kf) - 1)])
    np.testing.assert_allclose(rate_energy(pre.kRb, pre.delta_R, pre.kf_samples), direct, rtol=1e-8)


def test_estimate_without_leverage_is_the_plain_ml_variance():
    """With V = 0 (no fitted states) and C0 = 0, ℓ̃ is the Gaussian likelihood of r_k ~ N(0, s B_k I):
    its maximiser is s = Σ|r_k|²/B_k / (3n), computed here in closed form."""
    rng = np.random.default_rng(0)
    n = 400
    B = rng.uniform(0.5, 2.0, n) * 1e-4
    s_true = 0.02**2
    r = rng.normal(size=(n, 3)) * np.sqrt(s_true * B)[:, None]
    cov = (s_true * B)[:, None, None] * np.eye(3)
    s, _ = estimate_rate_variance(r, np.zeros((n, 3, 3)), cov, B, s_true)
    expected = np.sum(np.sum(r**2, 1) / B) / (3 * n)
    assert s == pytest.approx(expected, rel=1e-3)


def _simulate(kappa: float, sigma_d: float, sigma_u: float, seed: int):
    rng = np.random.default_rng(seed)
    L, K, dt = 20, 301, 0.01
    n = L * (K - 1) + 1
    w = _rates(n, dt, rng)
    sd = np.sqrt(sigma_d**2 + kappa**2 * np.sum(w**2, 1))
    w_meas = w + rng.normal(size=(n, 3)) * sd[:, None]
    R = np.empty((n, 3, 3))
    R[0] = np.eye(3)
    inc = expmap(w * dt)
    for j in range(n - 1):
        R[j + 1] = R[j] @ inc[j]
    kf, skf = keyframe_layout(n, L)
    meas = [R[s] @ expmap(rng.normal(size=3) * sigma_u) for s in kf]
    return w_meas, np.full(n, dt), kf, skf, meas


def _solve(w_meas, dt, kf, skf, meas, sigma_d, sigma_u, kappa, values):
    pre = preintegrate(w_meas, dt, kf, skf, np.zeros(3), np.full(3, sigma_d), kappa)
    graph = gtsam.NonlinearFactorGraph()
    for f in ahrs_factors(pre, keys.rot, keys.bias(0), np.full(3, sigma_d)):
        graph.add(f)
    unary = gtsam.noiseModel.Isotropic.Sigma(3, sigma_u)
    for k, Rm in enumerate(meas):
        graph.add(gtsam.PriorFactorRot3(keys.rot(k), gtsam.Rot3(Rm), unary))
    graph.add(gtsam.PriorFactorVector(keys.bias(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    if values is None:
        values = gtsam.Values()
        for k, Rm in enumerate(meas):
            values.insert(keys.rot(k), gtsam.Rot3(Rm))
        values.insert(keys.bias(0), np.zeros(3))
    out = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return pre, SimpleNamespace(graph=graph, blocks=[]), out


@pytest.mark.parametrize("start", [0.003, 0.03])
def test_reestimated_kappa_recovers_simulated_value(start):
    """A keyframe chain whose gyro has white noise σ_d + κ|ω| (κ = 0.01) and noisy absolute orientations:
    the ML rounds (solve, κ step) recover κ within 15 % from a start 3× too small or too large."""
    kappa, sigma_d, sigma_u = 0.01, 2e-3, 2e-3
    w_meas, dt, kf, skf, meas = _simulate(kappa, sigma_d, sigma_u, seed=7)
    state, values = {"kappa": start}, None
    for _ in range(25):
        pre, prob, values = _solve(w_meas, dt, kf, skf, meas, sigma_d, sigma_u, state["kappa"], values)
        if update_rate_error(state, prob, values, pre) < 0.01:
            break
    assert state["kappa"] == pytest.approx(kappa, rel=0.15)
