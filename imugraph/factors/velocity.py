"""Linear acceleration as motion, not noise: keyframe velocities driven by the accelerometer, with a
bounded-velocity (Gauss–Markov) prior.

The accelerometer measures specific force, b_acc = bRn (n_acc − n_grav) + e (DESIGN.md). Integrated
between keyframes k and k+1 (samples j of interval k attached through the preintegrated gyro ΔR_kj):

    v_{k+1} = v_k + n_grav Δt_k + R_k Δv_k + e_k,     Δv_k = Σ_j ΔR_kj a_j dt_j     (Forster et al. 2017,
                                                                                    velocity part, eq. 33)
    Σ_e,k = Σ_j (σ_a² + κ_a² |a_j|²) dt_j² · I       (white noise, plus scale/misalignment error κ_a)

Residual e_k = v_{k+1} − v_k − n_grav Δt_k − R_k Δv_k; Jacobians (right perturbation R_k Exp(ξ)):

    ∂e_k/∂ξ = R_k [Δv_k]×,   ∂e_k/∂v_k = −I,   ∂e_k/∂v_{k+1} = I

A sensor carried by a person or a robot arm does not drift away: its velocity stays bounded. That is
the information that separates tilt from linear acceleration (a tilt error δ makes the integrated
velocity drift by g·δ per second). It enters as a first-order Gauss–Markov prior on the velocity,
stationary with standard deviation σ_v and correlation time τ_v:

    v_0 ~ N(0, σ_v² I),   v_{k+1} = φ_k v_k + w_k,   φ_k = exp(−Δt_k/τ_v),   w_k ~ N(0, σ_v² (1 − φ_k²) I)

(σ_v, τ_v may also differ per nav axis — a horizontal and a vertical process — each axis its own chain;
they can be estimated in the ML loop: imugraph.calibration.velocity_process.)

An accelerometer bias b_a (sensor frame, slowly varying) would otherwise make the integrated velocity
drift as the sensor turns, which the bounded-velocity prior can only answer with a tilt error. It enters
the increment linearly, with B_k = Σ_j ΔR_kj dt_j:

    v_{k+1} = v_k + n_grav Δt_k + R_k (Δv_k − B_k b_k),   ∂e_k/∂b_k = R_k B_k,
    b_{k+1} = b_k + w_b,k,   w_b,k ~ N(0, σ_b² Δt_k I)           (random walk; b_0 ~ N(0, σ_b0² I))

Treating linear acceleration as white accelerometer noise (the per-sample gravity factor) is the
limit this model replaces: real linear acceleration is strongly correlated in time and has no DC part.
"""

from __future__ import annotations

import numpy as np

from imugraph.factors.gaps import GAP_ACC_WALK, gap_variance, has_gap
from imugraph.geometry import skew


def velocity_increments(kRb: np.ndarray, sample_kf: np.ndarray, b_acc: np.ndarray, dt: np.ndarray,
                        n_keyframes: int, sigma_acc: np.ndarray, rate_error: float,
                        gap_walk: float | None = GAP_ACC_WALK) -> tuple[np.ndarray, np.ndarray]:
    """Δv_k in keyframe k's body frame (K−1, 3) and the std of its error (K−1,), m/s.

    Args:
        kRb: (N, 3, 3) ΔR_kj of each sample; sample_kf: (N,) keyframe of each sample; b_acc: (N, 3) m/s²;
        dt: (N,) step from sample j to j+1, s; sigma_acc: (3,) white noise std per sample, m/s²;
        rate_error: κ_a, relative accelerometer error (scale factor, misalignment).
        gap_walk: q_a of the steps with missing time (factors.gaps eq. G1); None: off.
    """
    a_k = np.einsum("nij,nj->ni", kRb, b_acc) * dt[:, None]
    dv = _sum_by(sample_kf, a_k, n_keyframes)
    var = (float(np.mean(np.asarray(sigma_acc, float) ** 2)) + rate_error**2 * np.sum(b_acc**2, axis=1)) * dt**2
    T = float(np.median(dt)) if gap_walk is not None else 0.0
    if gap_walk is not None and has_gap(dt, T):                         # samples that never arrived: gaps eq. (G1)
        var = var + gap_variance(dt, T, gap_walk)
    var_k = np.bincount(sample_kf, weights=var, minlength=n_keyframes)
    # the last keyframe starts no interval (its own sample has no successor)
    return dv[:-1], np.sqrt(np.maximum(var_k[:-1], 1e-12))


def bias_integrals(kRb: np.ndarray, sample_kf: np.ndarray, dt: np.ndarray, n_keyframes: int) -> np.ndarray:
    """B_k = Σ_j ΔR_kj dt_j (K−1, 3, 3): how a sensor-frame accelerometer bias enters Δv_k."""
    return _sum_by(sample_kf, kRb * dt[:, None, None], n_keyframes)[:-1]


def _sum_by(index: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """Σ of the rows of x (M, …) per bin index (M,) → (n, …), one bincount per component (in row order,
    like np.add.at, which is an order of magnitude slower)."""
    flat = x.reshape(len(x), -1)
    out = np.stack([np.bincount(index, weights=flat[:, c], minlength=n) for c in range(flat.shape[1])], axis=1)
    return out.reshape((n,) + x.shape[1:])


def velocity_model(nRk: np.ndarray, v: np.ndarray, dv: np.ndarray, dt_k: np.ndarray, g: float,
                   b_a: np.ndarray | None = None, B: np.ndarray | None = None):
    """Residuals e (K−1, 3) and Jacobians J_R (K−1, 3, 3) of the velocity-increment factors.

    nRk (K, 3, 3), v (K, 3) nav-frame velocities, dv (K−1, 3) body-frame increments, dt_k (K−1,) s;
    optional accelerometer bias b_a (K, 3) with B (K−1, 3, 3) from `bias_integrals`.
    ∂e/∂v_k = −I, ∂e/∂v_{k+1} = I and ∂e/∂b_k = R_k B_k are not returned.
    """
    n_grav = np.array([0.0, 0.0, -g])
    R = nRk[:-1]
    if b_a is not None:
        dv = dv - np.einsum("kij,kj->ki", B, b_a[:-1])
    e = v[1:] - v[:-1] - n_grav[None, :] * dt_k[:, None] - np.einsum("kij,kj->ki", R, dv)
    J_R = R @ skew(dv)
    return e, J_R


def gauss_markov(dt_k: np.ndarray, sigma_v: float, tau_v: float) -> tuple[np.ndarray, np.ndarray]:
    """φ_k = exp(−Δt_k/τ_v) and the std of w_k, σ_v √(1 − φ_k²), for each keyframe interval."""
    phi = np.exp(-np.asarray(dt_k, float) / max(tau_v, 1e-9))
    return phi, sigma_v * np.sqrt(np.maximum(1.0 - phi**2, 1e-12))


def gauss_markov_axes(dt_k: np.ndarray, sigma_v, tau_v) -> tuple[np.ndarray, np.ndarray]:
    """`gauss_markov` per nav axis: σ_v, τ_v scalars or (3,) (x, y, z), e.g. one horizontal and one vertical
    process; returns φ and σ_w as (K−1, 3)."""
    dt = np.asarray(dt_k, float)[:, None]
    tau = np.maximum(np.broadcast_to(np.asarray(tau_v, float), (3,)), 1e-9)[None, :]
    phi = np.exp(-dt / tau)
    sigma = np.broadcast_to(np.asarray(sigma_v, float), (3,))[None, :]
    return phi, sigma * np.sqrt(np.maximum(1.0 - phi**2, 1e-12))


def gravity_from_velocity(nRk: np.ndarray, dv: np.ndarray, dt_k: np.ndarray) -> float:
    """g that closes the vertical velocity budget of a bounded motion: Σ_k (R_k Δv_k)_z − g T = 0.

    The magnitude at rest (median |a|) differs from the mean vertical specific force in motion by the
    accelerometer's scale error; 0.02 m/s² of mismatch is 4 m/s of vertical drift over 200 s, which the
    bounded-velocity prior would otherwise have to absorb.
    """
    up = np.einsum("kj,kj->k", nRk[:-1, 2, :], dv).sum()
    return float(up / np.sum(dt_k))


# A second-order velocity process (Options.estimate_velocity_process "…ar2"): a hand moving back and forth
# has velocities that anti-correlate at half its period (BROAD 15/16, optical: ρ(0.4 s) = −0.75 / −0.56),
# which no first-order process represents. At keyframe spacing Δt (uniform), per nav axis:
#
#     v_{k+1} = a_1 v_k + a_2 v_{k−1} + w_k,   w_k ~ N(0, q)         (AR(2); a_2 = 0: the chain above)
#
# stationary when a_1 + a_2 < 1, a_2 − a_1 < 1, a_2 > −1, with variance and lag-1 autocorrelation
# (Box & Jenkins, Time Series Analysis, eqs. 3.2.24 and 3.2.30 for p = 2):
#
#     γ_0 = q (1 − a_2) / [(1 + a_2)((1 − a_2)² − a_1²)],   ρ_1 = a_1 / (1 − a_2),
#
# which give the exact start of the chain: v_0 ~ N(0, γ_0), v_1 | v_0 ~ N(ρ_1 v_0, γ_0 (1 − ρ_1²)).


def ar2_stationary(a1: float, a2: float, q: float) -> tuple[float, float]:
    """(γ_0, ρ_1) of the stationary AR(2) process (comment above); ValueError when not stationary."""
    if not (a1 + a2 < 1.0 and a2 - a1 < 1.0 and a2 > -1.0):
        raise ValueError(f"AR(2) velocity process: found a1={a1:.4g}, a2={a2:.4g}, expected a stationary pair")
    gamma0 = q * (1.0 - a2) / ((1.0 + a2) * ((1.0 - a2) ** 2 - a1**2))
    return float(gamma0), float(a1 / (1.0 - a2))


def ar2_residuals(v: np.ndarray, a1: float, a2: float, q: float) -> np.ndarray:
    """Whitened AR(2) terms of velocities v (K, n): rows 0, 1 the stationary start (v_0, v_1 | v_0), then
    (v_{k+1} − a_1 v_k − a_2 v_{k−1})/√q for k = 1 … K−2; (K, n). Linear in v."""
    gamma0, rho1 = ar2_stationary(a1, a2, q)
    r = np.empty_like(np.asarray(v, float))
    r[0] = v[0] / np.sqrt(gamma0)
    r[1] = (v[1] - rho1 * v[0]) / np.sqrt(gamma0 * (1.0 - rho1**2))
    r[2:] = (v[2:] - a1 * v[1:-1] - a2 * v[:-2]) / np.sqrt(q)
    return r
