"""The gyro's rate-proportional noise κ re-estimated in the ML loop (Kok & Schön 2016, sec. IV: the noise
covariances are estimated by maximum likelihood, alternated with the state solve).

Model (factors/gyro.py): the per-sample gyro error has variance σ_d² + κ²|ω_j|², so the preintegrated
rotation of keyframe interval k has the (isotropic in the κ part) covariance

    Σ_k(s) = C0_k + s·B_k·I,    s = κ²,   B_k = Σ_j |ω_j − b̂|² Δt_j² = Σ_j |θ_j|²,   C0_k the σ_d part.

σ_d is measured at rest (where B_k = 0) and kept; s is the one free variance component. With r̂_k the gyro
factor's residual at the MAP solution and V_k = J_k P J_kᵀ its posterior covariance (P: the joint marginal
covariance of R_k, R_{k+1}, J_k = [−R_{k+1}ᵀR_k, I], the residual's Jacobian for small residuals), the
marginal (restricted) likelihood's score in s is (linear-Gaussian model, e.g. Harville 1977)

    ∂ℓ/∂s = ½ Σ_k [ r̂_kᵀ Σ_k⁻¹ B_k Σ_k⁻¹ r̂_k − tr(Σ_k⁻¹ B_k) + tr(Σ_k⁻¹ B_k Σ_k⁻¹ V_k) ].

A chain of between-factors absorbs most of its own residuals (leverage h_k = tr(Σ_k⁻¹V_k)/3 near 1 when the
gyro dominates each keyframe's information), so the plain EM step crawls. As for the other channels
(calibration/noise.py: σ² = Σ e²/(n − p)) the leverage is held at the current solution and the
dof-corrected likelihood is maximised in s:

    ℓ̃(s) = −½ Σ_k [ (1 − h_k) log|Σ_k(s)| + r̂_kᵀ Σ_k(s)⁻¹ r̂_k ]                    (per-interval REML form)

whose score equals ∂ℓ/∂s at the current s when V_k scales with Σ_k. One such step per ML round; the rounds
iterate it to the fixed point (tests/test_c2_gyro_rate.py: a simulated chain recovers a known κ).

Measured on BROAD (benchmarks/c2_noise_trace.py, broad_published.py --opt estimate_gyro_rate_error=True),
hence off by default (Options.estimate_gyro_rate_error): the estimate is ≈ 0.0097 on 06 (the default 0.01),
0.033 on 02 (0.475 → 0.459°) and runs to the 0.1 ceiling on 36 (1.32 → 2.23°): the gyro factors'
residuals carry the other channels' unmodelled errors (attached magnet), which the white κ|ω| term then
absorbs. With correlated_noise the 17-trial mean is 0.71° (0.68° without κ: 04 +0.18°, 21 +0.23°).
Leverage h ≈ 0.98 on BROAD (the gyro dominates each keyframe), so one step per round moves κ slowly
(06 from 0.002: 0.0042 → 0.0089 over 8 rounds). Cost: one gtsam.Marginals and K−1 joint marginals per
round (≈ 0.3–0.5 s on a BROAD trial).
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.geometry import logmap


def rate_energy(kRb: np.ndarray, delta_R: np.ndarray, kf_samples: np.ndarray) -> np.ndarray:
    """B_k = Σ_j |θ_j|² (K−1,) of each keyframe interval from a preintegration's rotations alone.

    Within interval k, kRb_{j+1} = kRb_j Exp(θ_j); the interval's last step ends at ΔR_k (Exp(θ_last) =
    kRb_lastᵀ ΔR_k). θ_j = (ω_j − b̂)Δt_j is the bias-corrected rotation increment of sample j."""
    n = kRb.shape[0]
    K = len(kf_samples)
    nxt = np.empty_like(kRb)
    nxt[:-1] = kRb[1:]
    nxt[-1] = np.eye(3)                                    # (overwritten below when it ends an interval)
    last = np.asarray(kf_samples[1:], int) - 1            # last sample of interval k (k = 0..K−2)
    nxt[last] = delta_R
    rel = np.einsum("nji,njk->nik", kRb[:n], nxt)          # kRb_jᵀ kRb_{j+1} = Exp(θ_j)
    th2 = np.sum(logmap(rel) ** 2, axis=1)
    kf_of = np.searchsorted(kf_samples, np.arange(n), side="right") - 1
    keep = kf_of < K - 1                                    # samples after the last keyframe: no interval
    return np.bincount(kf_of[keep], weights=th2[keep], minlength=K - 1)[:K - 1]


def gyro_residual_moments(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n: int,
                          gfg: gtsam.GaussianFactorGraph, rot_key=keys.rot) -> tuple[np.ndarray, np.ndarray]:
    """Residuals r̂ (n, 3) of the first n factors of graph (the AHRSFactors, interval k between rot_key(k) and
    rot_key(k+1)) and their posterior covariances V (n, 3, 3) from the linearised problem gfg."""
    r = np.array([graph.at(k).unwhitenedError(values) for k in range(n)]).reshape(n, 3)
    marg = gtsam.Marginals(gfg, values)
    V = np.empty((n, 3, 3))
    for k in range(n):
        P = marg.jointMarginalCovariance([rot_key(k), rot_key(k + 1)]).fullMatrix()
        Ri, Rj = values.atRot3(rot_key(k)).matrix(), values.atRot3(rot_key(k + 1)).matrix()
        J = np.hstack([-Rj.T @ Ri, np.eye(3)])               # ∂r/∂(δ_i, δ_j), right perturbations, small r
        V[k] = J @ P @ J.T
    return r, V


def estimate_rate_variance(r: np.ndarray, V: np.ndarray, cov: np.ndarray, energy: np.ndarray,
                           s_now: float, s_max: float = 0.1**2) -> tuple[float, dict]:
    """One dof-corrected ML step for s = κ² (module docstring); returns s and diagnostics.

    Args: r (n,3) residuals, V (n,3,3) their posterior covariances, cov (n,3,3) the factors' Σ_k(s_now),
    energy (n,) B_k, s_now the κ² they were built with, s_max the upper end of the search."""
    C0 = cov - s_now * energy[:, None, None] * np.eye(3)
    lam, U = np.linalg.eigh(0.5 * (C0 + np.transpose(C0, (0, 2, 1))))
    lam = np.maximum(lam, 1e-30)
    r_e2 = np.einsum("kji,kj->ki", U, r) ** 2                # r̂ in C0's eigenbasis, squared (n, 3)
    Sinv = np.linalg.inv(cov)
    h = np.clip(np.einsum("kij,kji->k", Sinv, V) / 3.0, 0.0, 0.999)   # leverage of each gyro factor
    keep = energy >= 0

    def neg(s: np.ndarray) -> np.ndarray:                    # −ℓ̃(s) on a grid of s values (G,)
        d = lam[None] + s[:, None, None] * energy[None, :, None]            # (G, n, 3)
        return 0.5 * np.sum(((1.0 - h)[None, :, None] * np.log(d) + r_e2[None] / d)[:, keep], axis=(1, 2))

    grid = np.r_[0.0, np.geomspace(1e-12, s_max, 160)]
    f = neg(grid)
    i = int(np.argmin(f))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    for _ in range(40):                                      # golden-section refinement in [lo, hi]
        a, b = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
        fa, fb = neg(np.array([a, b]))
        lo, hi = (lo, b) if fa < fb else (a, hi)
    s = 0.5 * (lo + hi)
    return float(s), {"leverage_mean": float(h.mean()), "dof": float(3.0 * np.sum(1.0 - h[keep]))}


def update_rate_error(state: dict, prob, values: gtsam.Values, pre, record: dict | None = None,
                      kappa_max: float = 0.1) -> float:
    """ML-loop step: κ re-estimated from the round's solution; state["kappa"] updated in place.

    prob: the round's Problem (graph whose first K−1 factors are the AHRSFactors, blocks); pre: the round's
    Preintegration (built with κ = state["kappa"]). Returns |log(κ_new/κ_old)| (for the loop's settling
    test); records κ and the mean leverage in record["gyro_rate_error"]."""
    n = len(pre.delta_R)
    if n < 2:
        return 0.0
    gfg = prob.graph.linearize(values)
    for b in prob.blocks:
        gfg.push_back(b.linearize(values))
    r, V = gyro_residual_moments(prob.graph, values, n, gfg)
    energy = rate_energy(pre.kRb, pre.delta_R, pre.kf_samples)
    k_old = float(state["kappa"])
    s, diag = estimate_rate_variance(r, V, np.asarray(pre.cov, float), energy, k_old**2, kappa_max**2)
    k_new = float(np.sqrt(max(s, 1e-10)))
    state["kappa"] = k_new
    if record is not None:
        record["gyro_rate_error"] = {"kappa": k_new, **diag}
    return abs(float(np.log((k_new + 1e-3) / (k_old + 1e-3))))      # relative, floored near κ = 0
