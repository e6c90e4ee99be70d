"""σ_p of the bounded position (graphs/velocity_block.py (P1)) estimated per recording by EM (task J, issue 2c).

Why: a fixed σ_p = 1 m (Options.position_sigma) removes the phantom velocity of the BROAD rotation trials (H11,
docs/results_issue2.md session 16), but it was chosen on BROAD and a bounded position is wrong for a sensor that
travels. As σ_v, τ_v of the velocity process (calibration/velocity_process.py), σ_p is re-estimated every ML round
from the round's smoothed positions and their posterior covariances (Shumway & Stoffer 1982 M-step), τ_p held:

    p_0 ~ N(0, σ_p² I),   p_{k+1} = φ_k p_k + w_k,   φ_k = exp(−Δt_k/τ_p),   w_k ~ N(0, σ_p² (1 − φ_k²) I)   (P1)

    σ̂_p² = [ E|p_0|² + Σ_k E|p_{k+1} − φ_k p_k|² / (1 − φ_k²) ] / (3K)                                     (J1)
    E|p_{k+1} − φ p_k|² = |m_{k+1} − φ m_k|² + 3 (P_{k+1} + φ² P_k − 2φ C_k)        (per axis, isotropic chain)

m_k: smoothed positions; P_k = Var(p_k), C_k = Cov(p_k, p_{k+1}) per axis from the posterior of the linear
(velocity, position) chain at the round's orientations (robust weights held), interleaved x = (v_0, p_0, v_1, …):
its precision is banded (bandwidth 4 with the AR(2) process) and the same for the three nav axes (isotropic
process, isotropic increments' weights), so Takahashi's recursion (velocity_process.banded_inverse_bands) gives
the bands of its inverse once per round in O(K). As for the velocity process these covariances ignore the
orientation uncertainty (a lower bound: EM leans towards a tighter σ_p). A travelling sensor's positions spread
over tens of metres, and (J1) follows them up (σ̂_p grows round by round; `POSITION_SIGMA_BOUNDS[1]` is the
"off" end: a prior that wide no longer bounds anything at recording lengths).

Measured and NOT recommended (Options.estimate_position_sigma, benchmarks/j2_travel.py): the held orientations
hide the tilt that the bound bends, so a travelling sensor's positions shrink to the prior and EM follows them:
a simulated 220 m walk ends at σ̂_p = 0.51 m (0.484° → 1.093°), a 1.4 km drive at 2.6 m (2.78° → 3.73°); the
whole-posterior selection of calibration/position_select.py (J2) replaces it. The (v, p) chain here is reused there.

`inner` > 1 repeats E-step and M-step at the round's orientations (E-step: the chain's posterior mean, a banded
solve, as calibration/velocity_em.py does for the velocity process), so the round hands the next solve the
chain's own maximiser instead of one EM step.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded

from imugraph.calibration.velocity_em import increment_rhs
from imugraph.calibration.velocity_process import banded_inverse_bands, chain_bands
from imugraph.graphs.velocity_block import POSITION_KIN_SIGMA

POSITION_SIGMA_BOUNDS = (0.05, 1.0e4)     # m: a hand's tremor … effectively no bound


def vp_bands(block, nRk: np.ndarray, s: np.ndarray, sigma_p: float, tau_p: float,
             sigma_kin: float = POSITION_KIN_SIGMA) -> np.ndarray:
    """Lower-form bands (5, 2K) of the (v, p) chain's precision for ONE nav axis (x axis of chain_bands; the
    three are equal for an isotropic chain), interleaved index v_k → 2k, p_k → 2k+1: the velocity chain's
    bands (chain_bands), the kinematic rows (p_{k+1} − p_k − Δt_k v_k)/σ_kin and the (P1) prior."""
    K = block.n_keyframes
    ab_v = chain_bands(block, nRk, s)[:, :, 0]             # (3, K): Λ_vv(j+i, j)
    ab = np.zeros((5, 2 * K))
    for i in range(3):                                      # v_{j+i}, v_j → offset 2i at column 2j
        ab[2 * i, 0:2 * K:2] += ab_v[i]
    dt = np.asarray(block.dt_k, float)
    kin = 1.0 / sigma_kin**2
    iv, ip = 2 * np.arange(K - 1), 2 * np.arange(K - 1) + 1   # v_k, p_k of interval k (p_{k+1} at ip + 2)
    # coefficients (−Δt, −1, +1) on (v_k, p_k, p_{k+1}): outer product, lower triangle
    ab[0, iv] += kin * dt**2
    ab[0, ip] += kin
    ab[0, ip + 2] += kin
    ab[1, iv] += kin * dt                  # (p_k, v_k):     (−1)(−Δt)
    ab[3, iv] += -kin * dt                 # (p_{k+1}, v_k): (+1)(−Δt)
    ab[2, ip] += -kin                      # (p_{k+1}, p_k): (+1)(−1)
    phi = np.exp(-dt / max(float(tau_p), 1e-9))
    bw = 1.0 / (float(sigma_p) ** 2 * np.maximum(1.0 - phi**2, 1e-12))
    ab[0, 1] += 1.0 / float(sigma_p) ** 2
    ab[0, ip] += bw * phi**2
    ab[0, ip + 2] += bw
    ab[2, ip] += -bw * phi
    return ab


def posterior_vp(block, nRk: np.ndarray, s: np.ndarray, sigma_p: float, tau_p: float):
    """(K, 3) velocity and position means of the (v, p) chain at orientations nRk (robust weights at s): the
    minimiser of the increments' cost, the velocity process and (P1), as velocity_em.posterior_mean."""
    eta = np.zeros((2 * block.n_keyframes, 3))
    eta[0::2] = increment_rhs(block, nRk, s)               # the v_k rows; the p_k rows' right-hand side is 0
    x = solveh_banded(vp_bands(block, nRk, s, sigma_p, tau_p), eta, lower=True)
    return x[0::2], x[1::2]


def position_moments(block, nRk: np.ndarray, s: np.ndarray, sigma_p: float, tau_p: float):
    """Per-axis posterior Var(p_k) (K,) and Cov(p_k, p_{k+1}) (K−1,) of the (v, p) chain."""
    Z = banded_inverse_bands(vp_bands(block, nRk, s, sigma_p, tau_p))      # (5, 2K): Z_{j+i, j}
    return Z[0, 1::2], Z[2, 1:-2:2]


def m_step(m: np.ndarray, P: np.ndarray, C: np.ndarray, dt: np.ndarray, tau_p: float) -> float:
    """σ̂_p of (J1) from means m (K, 3), per-axis variances P (K,) and lag-1 covariances C (K−1,)."""
    K = len(m)
    phi = np.exp(-np.asarray(dt, float) / max(float(tau_p), 1e-9))
    innov = np.sum((m[1:] - phi[:, None] * m[:-1]) ** 2, axis=1) + 3.0 * (P[1:] + phi**2 * P[:-1] - 2 * phi * C)
    total = np.sum(m[0] ** 2) + 3.0 * P[0] + np.sum(innov / np.maximum(1.0 - phi**2, 1e-12))
    return float(np.sqrt(max(total, 0.0) / (3 * K)))


def update_position_sigma(vel_state: dict, block, nRk: np.ndarray, positions: np.ndarray, tau_p: float,
                          inner: int = 1, record: dict | None = None, tol: float = 1e-3) -> float:
    """EM step(s) of σ_p (J1) from a round's solution; sets vel_state["pos_sigma"], returns |Δ ln σ_p|.

    positions: (K, 3) the round's smoothed positions (the E-step's means); block: the round's VelocityBlock
    (with its σ_p in `position`); inner: EM steps at the round's orientations (module docstring)."""
    if block is None or block.B is not None or block.position is None:
        return 0.0
    sigma0 = float(block.position[0])
    s = np.asarray(vel_state["s"], float)
    sigma, m = sigma0, np.asarray(positions, float)
    lo, hi = POSITION_SIGMA_BOUNDS
    for it in range(max(1, int(inner))):
        if it > 0:                          # E-step at the held orientations under the current σ_p
            _, m = posterior_vp(block, nRk, s, sigma, tau_p)
        P, C = position_moments(block, nRk, s, sigma, tau_p)
        new = float(np.clip(m_step(m, P, C, block.dt_k, tau_p), lo, hi))
        step = abs(np.log(new / sigma))
        sigma = new
        if step < tol:
            break
    vel_state["pos_sigma"] = sigma
    if record is not None:
        record["position_sigma"] = sigma
        record["position_spread"] = float(np.sqrt(np.mean(np.sum((m - m.mean(axis=0)) ** 2, axis=1))))
    return float(abs(np.log(sigma / sigma0)))
