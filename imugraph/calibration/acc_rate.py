"""The accelerometer's motion-dependent error κ_a re-estimated in the ML loop (Kok & Schön 2016, sec. IV: the
noise covariances are estimated by maximum likelihood, alternated with the state solve) — the velocity-chain
analogue of the gyro's κ (calibration/gyro_rate.py). Opt-in: Options.estimate_acc_rate_error.

Model (factors/velocity.py): the velocity increment of keyframe interval k, Δv_k = Σ_j ΔR_kj a_j dt_j, has the
isotropic error covariance

    Σ_e,k(s) = d_k(s) I,   d_k(s) = c0_k + s·A_k,   s = κ_a²,   A_k = Σ_j |a_j|² dt_j²,   c0_k = mean(σ_a²) Σ_j dt_j²  (1)

σ_a is measured at rest (where the specific force is gravity alone) and kept; s is the one free variance
component. At the round's orientations R_k (and accelerometer bias, if any) the velocity chain is linear and
Gaussian, per nav axis i:

    y_k,i = v_{k+1,i} − v_{k,i} + e_k,i,   y_k = R_k Δv_k + n_grav Δt_k,   e_k,i ~ N(0, d_k(s) / w_k)          (2)

with the velocity process of the round (first-order Gauss–Markov or AR(2), imugraph.factors.velocity) as the
prior of v and w_k the increment's robust (Huber) weight at the solution. s is estimated by maximising the
marginal likelihood of the increments, the states integrated out — the prediction-error decomposition of a
Kalman filter on x_k = (v_{k+1}, v_k) (Schweppe 1965; Harvey 1989, sec. 3.4):

    ℓ(s) = −½ Σ_i Σ_k [ log S_k,i(s) + ν_k,i(s)² / S_k,i(s) ],   ν = y_k,i − H x̂_k|k−1,   S = H P_k|k−1 Hᵀ + d_k(s)/w_k,
    H = [1, −1]                                                                                             (3)

One maximisation per ML round (grid in s, then a bounded 1-D search); the rounds iterate it with the states.
Why not a residual-based (EM or leverage-held REML) step as for the gyro: one increment fixes v_{k+1} − v_k
almost alone (leverage ≈ 0.999 on simulations and BROAD), so the residuals carry almost nothing, E|ê_k|² grows
as d_k² rather than d_k, and that step oscillates or stalls at 0; the information on s lies in how the
integrated increments wander against the bounded-velocity prior, which (3) uses exactly.

The free maximiser κ_ml is searched on [0, KAPPA_SEARCH_MAX]; the estimate is held in [floor, KAPPA_MAX] (floor:
Options.acc_rate_error, the setting, as "bounded" treats σ_v: the estimate may only loosen the accelerometer).
Neglected: the orientations' own uncertainty (tilt trades with the velocity drift) and rest priors.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from imugraph.factors.velocity import ar2_stationary, gauss_markov_axes, velocity_model

KAPPA_MAX = 0.1           # a MEMS accelerometer's scale/misalignment error is a few %, not 10 %
KAPPA_SEARCH_MAX = 0.3    # range of the free maximiser (reported; beyond KAPPA_MAX: not identifiable)


def force_energy(b_acc: np.ndarray, dt: np.ndarray, sample_kf: np.ndarray, n_keyframes: int) -> np.ndarray:
    """A_k = Σ_j |a_j|² dt_j² (K−1,) of each keyframe interval, eq. (1) (the last keyframe starts none)."""
    e = np.sum(np.asarray(b_acc, float) ** 2, axis=1) * np.asarray(dt, float) ** 2
    return np.bincount(sample_kf, weights=e, minlength=n_keyframes)[:n_keyframes - 1]


def process_matrices(block) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The velocity prior of a VelocityBlock as a state-space model on x_k = (v_{k+1}, v_k), per nav axis:
    P0 (3, 2, 2) the covariance of x_0 = (v_1, v_0); for k = 1 … K−2 the transition x_k = F_k x_{k−1} + (w_k, 0),
    F (K−2, 3, 2, 2) and the variance of w_k, q (K−2, 3)."""
    n = len(block.dt_k)
    if block.ar2 is None:
        phi, sigma_w = gauss_markov_axes(block.dt_k, block.sigma_v, block.tau_v)        # (K−1, 3)
        var0 = np.broadcast_to(np.asarray(block.sigma_v, float) ** 2, (3,))
        c01, var1 = phi[0] * var0, phi[0] ** 2 * var0 + sigma_w[0] ** 2                 # v_1 = φ_0 v_0 + w_0
        F = np.zeros((n - 1, 3, 2, 2))
        F[..., 0, 0], F[..., 1, 0] = phi[1:], 1.0
        q = sigma_w[1:] ** 2
    else:
        a1, a2, qa = block.ar2
        gamma0, rho1 = ar2_stationary(a1, a2, qa)
        var0, c01, var1 = np.full(3, gamma0), np.full(3, rho1 * gamma0), np.full(3, gamma0)
        F = np.zeros((n - 1, 3, 2, 2))
        F[..., 0, 0], F[..., 0, 1], F[..., 1, 0] = a1, a2, 1.0
        q = np.full((n - 1, 3), qa)
    P0 = np.stack([np.stack([var1, c01], -1), np.stack([c01, var0], -1)], -2)
    return P0, F, q


def marginal_log_lik(s: np.ndarray, y: np.ndarray, c0: np.ndarray, A: np.ndarray, w: np.ndarray,
                     P0: np.ndarray, F: np.ndarray, q: np.ndarray) -> np.ndarray:
    """ℓ(s) of eq. (3) (constant dropped) for G values s (G,) at once: increments y (K−1, 3), c0, A, w (K−1,),
    the process from `process_matrices`. Kalman filter per (s, axis), components written out (2×2)."""
    s = np.atleast_1d(np.asarray(s, float))[:, None]                 # (G, 1)
    shape = (s.shape[0], 3)
    m1, m2 = np.zeros(shape), np.zeros(shape)                        # x̂ = (v_{k+1}, v_k)
    p11, p12, p22 = (np.broadcast_to(P0[:, i, j], shape).copy() for i, j in ((0, 0), (0, 1), (1, 1)))
    ll = np.zeros(s.shape[0])
    r = (c0[:, None] + s.T * A[:, None]) / np.maximum(w, 1e-12)[:, None]   # (K−1, G): d_k(s)/w_k
    for k in range(len(y)):
        if k > 0:                                                   # predict: x_k = F_k x_{k−1} + (w_k, 0)
            f11, f12 = F[k - 1, :, 0, 0], F[k - 1, :, 0, 1]
            n1 = f11 * m1 + f12 * m2
            m2, m1 = m1, n1
            a = f11 * p11 + f12 * p12                                # (F P)_11, (F P)_12 with F's second row (1, 0)
            b = f11 * p12 + f12 * p22
            p11, p12, p22 = a * f11 + b * f12 + q[k - 1], a, p11
        S = p11 - 2.0 * p12 + p22 + r[k][:, None]                    # H P Hᵀ + d/w,  H = [1, −1]
        nu = y[k][None, :] - (m1 - m2)
        ll -= 0.5 * np.sum(np.log(S) + nu**2 / S, axis=1)
        g1, g2 = (p11 - p12) / S, (p12 - p22) / S                    # gain P Hᵀ / S
        m1, m2 = m1 + g1 * nu, m2 + g2 * nu
        p11, p12, p22 = p11 - g1 * g1 * S, p12 - g1 * g2 * S, p22 - g2 * g2 * S
    return ll


def estimate_acc_rate(y: np.ndarray, c0: np.ndarray, A: np.ndarray, w: np.ndarray, P0: np.ndarray,
                      F: np.ndarray, q: np.ndarray, s_max: float = KAPPA_SEARCH_MAX**2) -> tuple[float, dict]:
    """The maximiser s = κ_a² of eq. (3) in [0, s_max] (grid, then a bounded search between its neighbours)
    and diagnostics (ℓ at the maximum and at s = 0)."""
    grid = np.r_[0.0, np.geomspace(1e-8, s_max, 48)]
    f = -marginal_log_lik(grid, y, c0, A, w, P0, F, q)
    i = int(np.argmin(f))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    s, best = float(grid[i]), float(f[i])
    if hi > lo:
        res = minimize_scalar(lambda x: float(-marginal_log_lik(x, y, c0, A, w, P0, F, q)[0]), bounds=(lo, hi),
                              method="bounded", options={"xatol": 1e-3 * (hi - lo), "maxiter": 20})
        if res.fun < best:
            s, best = float(res.x), float(res.fun)
    return s, {"loglik_gain": float(f[0] - best), "at_edge": bool(i == len(grid) - 1)}


def update_acc_rate_error(opt, vel_state: dict, block, nRk: np.ndarray, pre, session,
                          record: dict | None = None) -> float:
    """ML-loop step (module docstring): κ_a re-estimated from the round's velocity chain, stored in
    vel_state["kappa_a"] (read by the next round's VelocityModel). Returns |log(κ_new/κ_old)| (floored near 0)
    for the loop's settling test; 0 when Options.estimate_acc_rate_error is off or there is no chain.

    Args: opt the Options; vel_state the ML loop's velocity state (s: (K, 3|6) solved states); block the
    round's VelocityBlock; nRk (K, 3, 3) the round's orientations; pre the round's Preintegration (sample_kf);
    session the Session the block was built from (acc, m/s²; dt, s); record: history entry to note κ_a in.
    """
    if not opt.estimate_acc_rate_error or block is None or vel_state.get("s") is None:
        return 0.0
    if block.n_keyframes < 3:
        return 0.0
    st = np.asarray(vel_state["s"], float)
    b_a = None if block.B is None else st[:, 3:]
    y = -velocity_model(nRk, np.zeros((block.n_keyframes, 3)), block.dv, block.dt_k, block.g, b_a, block.B)[0]
    _, _, w, *_ = block.terms(nRk, st)
    A = force_energy(session.acc, session.dt, pre.sample_kf, block.n_keyframes)
    k_old = float(vel_state.get("kappa_a", opt.acc_rate_error))
    c0 = np.maximum(block.sigma_dv**2 - k_old**2 * A, 1e-30)          # eq. (1) at the block's κ_a
    s, diag = estimate_acc_rate(y, c0, A, w, *process_matrices(block))
    k_ml = float(np.sqrt(s))
    k_new = float(np.clip(k_ml, opt.acc_rate_error, KAPPA_MAX))
    vel_state["kappa_a"] = k_new
    if record is not None:
        record["acc_rate_error"] = {"kappa_a": k_new, "kappa_ml": k_ml, **diag}
    return abs(float(np.log((k_new + 1e-3) / (k_old + 1e-3))))
