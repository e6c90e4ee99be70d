"""Maximum-likelihood parameters of a second-order (AR(2)) velocity process inside the ML loop (EM step).

A hand that moves back and forth has velocities that anti-correlate at half its period (BROAD 15/16,
optical velocities: ρ(0.4 s) = −0.75 / −0.56; benchmarks/v2_heading_evidence.py), which the first-order
Gauss–Markov chain (calibration/velocity_process.py) cannot represent. Per nav axis, at keyframe spacing Δt
(taken uniform: the median interval), imugraph.factors.velocity:

    v_{k+1} = a_1 v_k + a_2 v_{k−1} + w_k,   w_k ~ N(0, q),   stationary start (γ_0, ρ_1)

EM (Shumway & Stoffer 1982), as for the first-order chain: the E-step is the posterior of the velocity
states at the round's orientations — means m_k from the solve, covariances from the chain's banded
precision (bandwidth 2 with AR(2) terms; `banded_inverse_bands`, Takahashi's recursion). The M-step
maximises the expected log-density conditional on the first two states (the conditional AR likelihood):

    f(a) = Σ_k E(v_{k+1} − a_1 v_k − a_2 v_{k−1})²,   N = n_axes (K − 2),
    −log L(a, q) = (N/2) ln q + f(a) / (2q),        q̂(a) = f(a)/N (clipped by the bounds below)

with a on a grid over the stationary region, then a finer grid around the best point (f is quadratic in a,
so each evaluation is closed form). The bounds follow `process_bounds` of the first-order chain: with
(σ_lo, σ_hi) and τ_hi, φ_max = exp(−Δt/τ_hi), the lag-1 autocorrelation ρ_1 ≤ φ_max and, when the
characteristic roots (z² = a_1 z + a_2) are real, the slower one r = (a_1 + √(a_1² + 4a_2))/2 ≤ φ_max (no
decay slower than the first-order limit; complex roots — an oscillation — are not limited), the stationary std
√γ_0 within (σ_lo, σ_hi), and the innovation variance q ≥ σ_lo² (1 − φ_max²) (the one-step spread of the
loosest allowed first-order process: "bounded" keeps the short-term steps from tightening).

Mode "map_ar2" replaces that hard floor on q by a prior (MAP instead of ML for q; a_1, a_2 free in the
stationary region): the conjugate inverse-gamma prior IG(ν_0/2, ν_0 q_0/2) — ν_0 pseudo-innovations of variance
q_0 — centred on the floor value q_0 = σ_v² (1 − exp(−2Δt/τ_v)) of the settings (Gelman et al., Bayesian Data
Analysis, 3rd ed., sec. 3.3, the normal model with unknown variance; its mode, the +2 dropped):

    −log p(a, q | v) = ((N + ν_0)/2) ln q + (f(a) + ν_0 q_0) / (2q),    q̂(a) = (f(a) + ν_0 q_0) / (N + ν_0)

so the prior binds (q̂ → q_0) only where the data hold few innovations against ν_0.
"""

from __future__ import annotations

import numpy as np
from imugraph.calibration.velocity_process import chain_inverse_bands
from imugraph.factors.velocity import ar2_stationary

ROOT_MARGIN = 0.01          # distance kept from the edges of the stationary triangle
COARSE_STEP, FINE_STEP = 0.01, 0.0005


def lag_moments(m: np.ndarray, Z: np.ndarray) -> list[np.ndarray]:
    """E[v_k v_{k+l}] summed over axes for l = 0, 1, 2: means m (K, n), inverse bands Z (3, K, n)."""
    K = len(m)
    return [np.sum(m[:K - l] * m[l:] + Z[l, :K - l], axis=1) for l in range(3)]


def ar2_objective_terms(E: list[np.ndarray]) -> tuple[float, np.ndarray, np.ndarray]:
    """(Σ E v_{k+1}², Σ E[x v_{k+1}], Σ E[x xᵀ]) with x = (v_k, v_{k−1}), k = 1 … K−2, from `lag_moments`."""
    E0, E1, E2 = E
    syy = E0[2:].sum()
    sxy = np.array([E1[1:].sum(), E2.sum()])
    sxx = np.array([[E0[1:-1].sum(), E1[:-1].sum()], [E1[:-1].sum(), E0[:-2].sum()]])
    return float(syy), sxy, sxx


def fit_ar2(syy: float, sxy: np.ndarray, sxx: np.ndarray, N: int, sigma_bounds: tuple, phi_max: float,
            prior: tuple | None = None) -> tuple[float, float, float]:
    """(a_1, a_2, q) minimising the conditional −log L (module docstring) under the bounds; prior (q_0, ν_0):
    the inverse-gamma prior on q of mode "map_ar2" (module docstring) added, None: ML."""
    q_floor = sigma_bounds[0] ** 2 * (1.0 - phi_max**2)
    q0, nu0 = (0.0, 0.0) if prior is None else (float(prior[0]), float(prior[1]))

    def nll(a1, a2):
        f = syy - 2 * (a1 * sxy[0] + a2 * sxy[1]) + a1**2 * sxx[0, 0] + 2 * a1 * a2 * sxx[0, 1] + a2**2 * sxx[1, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            cfac = (1 + a2) * ((1 - a2) ** 2 - a1**2) / (1 - a2)       # γ_0 = q / cfac
            ok = ((a1 + a2 < 1 - ROOT_MARGIN) & (a2 - a1 < 1 - ROOT_MARGIN) & (a2 > -1 + ROOT_MARGIN)
                  & (a1 <= phi_max * (1 - a2))
                  & ((a1**2 + 4 * a2 < 0) | (a1 + np.sqrt(np.abs(a1**2 + 4 * a2)) <= 2 * phi_max)))
            q = np.maximum((f + nu0 * q0) / (N + nu0), np.maximum(q_floor, sigma_bounds[0] ** 2 * cfac))
            q = np.minimum(q, np.maximum(sigma_bounds[1] ** 2 * cfac, q_floor))
            val = 0.5 * (N + nu0) * np.log(q) + 0.5 * (f + nu0 * q0) / q
        return np.where(ok, val, np.inf), q

    best = None
    for step, half in ((COARSE_STEP, None), (FINE_STEP, 2 * COARSE_STEP)):     # coarse grid, then fine
        if half is None:
            g1, g2 = np.arange(-2.0, 2.0 + step, step), np.arange(-1.0, 1.0 + step, step)
        else:
            g1 = best[0] + np.arange(-half, half + step, step)
            g2 = best[1] + np.arange(-half, half + step, step)
        A1, A2 = np.meshgrid(g1, g2, indexing="ij")
        val, q = nll(A1, A2)
        i = np.unravel_index(np.argmin(val), val.shape)
        best = (float(A1[i]), float(A2[i]), float(q[i]))
    return best


def update_ar2(vel_state: dict, block, nRk: np.ndarray, record: dict | None, sigma_bounds: tuple,
               tau_bounds: tuple, prior: tuple | None = None) -> float:
    """One EM step of the AR(2) process from a round's solution: sets vel_state["ar2"] = (a_1, a_2, q) and,
    for the first-order consumers (Calibration, smooth_fixed), vel_state["sigma"] = √γ_0 and
    vel_state["tau"] = −Δt / ln ρ_1 (inside tau_bounds). Returns the largest change (|Δa|, |Δ ln q|)."""
    s = np.asarray(vel_state["s"], float)
    K = len(s)
    if K < 5:
        return 0.0
    Z = chain_inverse_bands(block, nRk, s)
    syy, sxy, sxx = ar2_objective_terms(lag_moments(s[:, :3], Z))
    dt = float(np.median(block.dt_k))
    phi_max = float(np.exp(-dt / tau_bounds[1]))
    if prior is not None:               # (σ_v, τ_v, ν_0) of the settings → (q_0, ν_0) at this spacing
        prior = (prior[0] ** 2 * (1.0 - np.exp(-2.0 * dt / prior[1])), prior[2])
    a1, a2, q = fit_ar2(syy, sxy, sxx, 3 * (K - 2), sigma_bounds, phi_max, prior)
    prev = vel_state.get("ar2")
    if prev is None:                    # the first-order chain as an AR(2) with a_2 = 0
        phi = np.exp(-dt / float(np.max(vel_state["tau"])))
        prev = (phi, 0.0, float(np.min(vel_state["sigma"])) ** 2 * (1 - phi**2))
    change = max(abs(a1 - prev[0]), abs(a2 - prev[1]), abs(np.log(q / prev[2])))
    gamma0, rho1 = ar2_stationary(a1, a2, q)
    vel_state["ar2"] = (a1, a2, q)
    vel_state["sigma"] = float(np.sqrt(gamma0))
    vel_state["tau"] = float(np.clip(-dt / np.log(np.clip(rho1, 1e-9, 1 - 1e-9)), *tau_bounds))
    if record is not None:
        record["velocity_ar2"] = [a1, a2, q]
        record["velocity_sigma"], record["velocity_tau"] = vel_state["sigma"], vel_state["tau"]
    return float(change)
