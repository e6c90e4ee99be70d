"""Axis alignment of the ellipsoid-calibrated magnetometer to the inertial axes (Kok et al. 2012).

Kok, Hol, Schön, Gustafsson, Luinge (FUSION 2012), initial estimate, alignment step. The ellipsoid
fit gives D₀, o₀ with
m̃_t = D₀⁻¹(y_t − o₀) of unit norm, but any D = D₀Q with Q orthogonal fits it equally well. With the
model y = D·bRn·n_mag + o (DESIGN.md) the calibrated field in the INERTIAL axes is

    m_b = D⁻¹(y − o) = R·m̃,     hence   D = D₀·Rᵀ,   o = o₀.

Inclination constraint: gravity and the field keep a constant angle. With the body "up" direction
u_b = bRn·e_z (the accelerometer direction at rest, +g up) and n_mag = [cos δ, 0, −sin δ],

    (R·m̃_t)ᵀ u_b,t = (bRn n_mag)ᵀ(bRn e_z) = n_magᵀ e_z = −sin δ        for every t   [inclination]

solved here by nonlinear least squares over (R, δ), R = Exp(φ) (rotation vector φ), from R = I and
sin δ₀ = −mean(m̃ᵀu_b), with a soft-L1 loss against samples where the field or acceleration is off.
Two departures from using acc/‖acc‖ directly, both needed on real data (BROAD): u_b comes from
`gravity_up` (the accelerometer averaged in the gyro-integrated frame; the raw direction is 3–15°
off during movement), and the magnetometer's lag behind the inertial sensors is estimated
(`estimate_mag_delay`) so that each field sample is paired with "up" at the same instant.

Which (R, δ) are identifiable. Linearise at the truth, R = Exp(φ), with m_b = bRn n_mag:
∂r_t = φᵀ(u_b × m_b) + cos δ·∂δ = −cos δ·(φᵀ e_b,t − ∂δ), where e_b,t = bRn_t·e_y is the body-frame
direction of the horizontal axis perpendicular to the field (n_mag × e_z = −cos δ·e_y). So (φ, ∂δ) =
(a, c) is unobservable iff aᵀe_b,t = c for all t, i.e. iff all e_b,t lie on one circle of the sphere.
Rotation about a single body axis (e_b turns about it) is the common case: then G·R with G about that
axis fits equally well (a 1-D family). Rotations about the field's perpendicular horizontal axis add
nothing (e_b does not move). Otherwise (R, δ) are identifiable, with a sensitivity that scales with
cos δ (weak at high dip: 0.36 at 69°). A right factor R·H is never hidden since m̃ takes many
directions. Gauge fix: a weak prior on φ (weight `PRIOR_WEIGHT` relative to the data) keeps R at the
start (magnetometer axes = inertial axes) along any unobservable direction, negligible otherwise.

Reflection: det(D) > 0 by construction (D₀ symmetric positive definite, R proper). A magnetometer
whose axes are mirrored relative to the inertial axes (D₀Q with det Q = −1, i.e. Q = −rotation) is
indistinguishable from a field of opposite dip: (−R m̃)ᵀu = −sin δ ⇔ (R m̃)ᵀu = sin δ. Directions alone
cannot tell them apart; `initial.py` can resolve it when the hemisphere is known.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from imugraph.geometry import expmap, quat_mul, quat_normalize, quat_to_rotmat, rotvec_to_quat, skew

PRIOR_WEIGHT = 1e-3   # per-parameter prior, relative to the square root of the number of samples
MAX_ROWS = 5000       # evenly spread subsample for speed


def _prefix_quat_product(dq: np.ndarray) -> np.ndarray:
    """Inclusive prefix products q_k = dq_0 ⊗ … ⊗ dq_k of (N, 4) quaternions (Hillis–Steele scan:
    ⌈log₂N⌉ vectorised steps instead of a per-sample loop; exact since ⊗ is associative)."""
    q = dq.copy()
    shift = 1
    while shift < q.shape[0]:
        q[shift:] = quat_mul(q[:-shift], q[shift:])
        shift *= 2
    return quat_normalize(q)


def gravity_up(b_gyr: np.ndarray, b_acc: np.ndarray, dt: np.ndarray,
               gyro_bias: np.ndarray | None = None, window_s: float = 4.0) -> np.ndarray:
    """Body "up" directions robust to linear acceleration.

    The gyro is integrated (strapdown, q_{k+1} = q_k ⊗ Exp(ω_k dt_k)) into a frame i that is fixed
    up to drift; there the specific force is i_acc = iRb·b_acc = iRn(n_acc_lin + g·e_z), and over a
    window of T seconds the linear part averages to Δv/T, so the windowed mean of i_acc points up.
    Rotated back: u_b,t = iRb,tᵀ·mean(i_acc)/‖·‖. On BROAD (slow trials) this is 0.3–0.4° from the
    optical "up" (median), against 3–4° for acc/‖acc‖ during movement.

    Args:
        b_gyr: (N, 3) rad/s. b_acc: (N, 3) m/s². dt: (N,) s, step from each sample to the next.
        gyro_bias: (3,) rad/s removed before integrating (drift over the window is what remains).
        window_s: averaging window T, s.

    Returns:
        (N, 3) unit vectors u_b (NaN where the accelerometer is not finite).
    """
    w = np.nan_to_num(np.asarray(b_gyr, float) - (0.0 if gyro_bias is None else gyro_bias))
    dq = rotvec_to_quat(w * np.asarray(dt, float)[:, None])
    iRb = quat_to_rotmat(np.concatenate([[[1.0, 0, 0, 0]], _prefix_quat_product(dq)[:-1]]))
    i_acc = np.einsum("nij,nj->ni", iRb, np.asarray(b_acc, float))
    ok = np.all(np.isfinite(i_acc), axis=1)
    n = max(1, int(round(window_s / max(float(np.median(dt)), 1e-9))))
    c = np.concatenate([np.zeros((1, 4)), np.cumsum(np.c_[np.where(ok[:, None], i_acc, 0.0), ok], 0)])
    k = np.arange(i_acc.shape[0])
    lo, hi = np.clip(k - n // 2, 0, len(k)), np.clip(k - n // 2 + n, 0, len(k))
    i_up = (c[hi, :3] - c[lo, :3]) / np.maximum(c[hi, 3] - c[lo, 3], 1.0)[:, None]
    b_up = np.einsum("nji,nj->ni", iRb, i_up)
    b_up /= np.linalg.norm(b_up, axis=1, keepdims=True)
    return np.where(ok[:, None], b_up, np.nan)


def estimate_mag_delay(t: np.ndarray, m_tilde: np.ndarray, b_gyr: np.ndarray,
                       max_delay_s: float = 0.05, window_s: float = 0.04,
                       max_rows: int = 4000) -> float:
    """Delay τ of the magnetometer behind the gyroscope (s; > 0: the magnetometer lags).

    A static field seen from a turning bodm obeys ṁ_b = m_b × ω. Over a window [t_j − h, t_j + h]:
    m(t_j + h) − m(t_j − h) ≈ [m_j]× (Ω(t_j + h − τ) − Ω(t_j − h − τ)), Ω the integrated gyro
    (Ω(t_k) = Σ_{i<k} ω_i dt_i, the strapdown convention q_{k+1} = q_k ⊗ Exp(ω_k dt_k)). Differences
    over a window rather than between neighbours keep magnetometer noise from swamping the fit. In the
    magnetometer axes the map is A = Rᵀ (times gyro scale), so for every τ on a grid of one gyro
    sample a free 3×3 A is fitted by linear least squares and τ minimises the residual (parabolic
    refinement). BROAD: 8.6–9.9 ms (≈ 2.7 samples) on every trial that rotates.

    Args:
        t: (N,) s. m_tilde: (N, 3) ellipsoid-calibrated field (NaN rows ignored). b_gyr: (N, 3) rad/s.
        max_delay_s: search range ±, s. window_s: difference window 2h, s.
        max_rows: magnetometer rows used (evenly thinned).

    Returns:
        τ in s (0.0 when the data hold too little rotation for a clear optimum).

    Solved for every lag of the grid at once (one least squares per lag was a third of the diagnosis'
    time): with S_j = [m_j]×, ΔΩ_j(τ) and Δm_j, the row block of vec(A) (row-major) is S_j ⊗ ΔΩ_jᵀ, so

        G(τ) = Σ_j (S_jᵀS_j) ⊗ (ΔΩ_j ΔΩ_jᵀ),   b(τ) = Σ_j (S_jᵀΔm_j) ⊗ ΔΩ_j,
        RSS(τ) = Σ_j |Δm_j|² − b(τ)ᵀ G(τ)⁺ b(τ).

    A window spanning a gap of m (NaN rows: a data gap, or the held-out blocks of the diagnosis'
    cross-validation) is dropped: its Δm is the change over the whole gap, far outside the small-angle
    model (BROAD 01 + 5.9 ms gyro delay: −0.4 and 0.0 ms on two folds' training samples with them, 3.6–3.9
    ms on every fold without). Any bodm-fixed view of a constant nav-frame vector works the same way
    (gravity for the accelerometer: imugraph.diagnose.effects.time_offset).
    """
    t = np.asarray(t, float)
    j = np.flatnonzero(np.all(np.isfinite(m_tilde), axis=1))
    if j.size < 20:
        return 0.0
    tj, mj = t[j], np.asarray(m_tilde, float)[j]
    step_m = float(np.median(np.diff(tj)))
    h = max(1, int(round(0.5 * window_s / step_m)))
    lo, mid, hi = np.arange(0, tj.size - 2 * h), np.arange(h, tj.size - h), np.arange(2 * h, tj.size)
    whole = tj[hi] - tj[lo] < 1.5 * 2 * h * step_m           # windows that span no gap (data gap, hidden block)
    lo, mid, hi = lo[whole], mid[whole], hi[whole]
    if mid.size < 20:
        return 0.0
    keep = np.linspace(0, mid.size - 1, min(mid.size, max_rows)).round().astype(int)
    lo, mid, hi = lo[keep], mid[keep], hi[keep]
    dm = mj[hi] - mj[lo]
    w_dt = np.nan_to_num(np.asarray(b_gyr, float)[:-1]) * np.diff(t)[:, None]
    omega = np.concatenate([np.zeros((1, 3)), np.cumsum(w_dt, axis=0)])           # Ω(t_k)
    step = float(np.median(np.diff(t)))
    taus = np.arange(-max_delay_s, max_delay_s + 0.5 * step, step)
    q_hi = (tj[hi][None, :] - taus[:, None]).ravel()
    q_lo = (tj[lo][None, :] - taus[:, None]).ravel()
    d_om = np.stack([np.interp(q_hi, t, omega[:, i]) - np.interp(q_lo, t, omega[:, i]) for i in range(3)],
                    axis=1).reshape(taus.size, -1, 3)                               # ΔΩ_j(τ) (L, M, 3)
    S = skew(mj[mid])                                                               # (M, 3, 3)
    StS = np.einsum("nik,nil->nkl", S, S).reshape(-1, 9)                            # (k, k') flattened
    Sdm = np.einsum("nik,ni->nk", S, dm)                                            # S_jᵀ Δm_j
    outer = (d_om[:, :, :, None] * d_om[:, :, None, :]).reshape(taus.size, -1, 9)   # (l, l') flattened
    G = np.matmul(StS.T[None], outer).reshape(taus.size, 3, 3, 3, 3)               # Σ_j over rows (BLAS)
    G = G.transpose(0, 1, 3, 2, 4).reshape(taus.size, 9, 9)                         # [(k,l), (k',l')]
    b = np.matmul(Sdm.T[None], d_om).reshape(taus.size, 9)                          # [(k,l)]
    total = float(np.sum(dm * dm))
    r = np.array([total - float(bl @ np.linalg.lstsq(Gl, bl, rcond=None)[0]) for Gl, bl in zip(G, b)])  # RSS(τ)
    k = int(np.argmin(r))
    if 1.0 - r[k] / total < 0.1 or k in (0, taus.size - 1):
        return 0.0
    den = r[k - 1] - 2 * r[k] + r[k + 1]
    return float(taus[k] + (0.5 * step * (r[k - 1] - r[k + 1]) / den if den > 0 else 0.0))


def _residuals(p: np.ndarray, m_tilde: np.ndarray, u_b: np.ndarray, w_prior: float) -> np.ndarray:
    """[inclination]: r_t = (Exp(φ) m̃_t)ᵀ u_b,t + sin δ, plus the gauge prior w·φ."""
    R = expmap(p[:3])
    r = np.einsum("ij,nj,ni->n", R, m_tilde, u_b) + np.sin(p[3])
    return np.concatenate([r, w_prior * p[:3]])


def _jacobian(p: np.ndarray, m_tilde: np.ndarray, u_b: np.ndarray, w_prior: float) -> np.ndarray:
    """(N + 3, 4) Jacobian of `_residuals`: Exp(φ + dφ) ≈ Exp(φ)·Exp(J_r(φ)dφ) gives
    ∂r_t/∂φ = −u_b,tᵀ R [m̃_t]× J_r(φ) and ∂r_t/∂δ = cos δ."""
    R = expmap(p[:3])
    Jr = _right_jacobian(p[:3])
    J_phi = -np.einsum("ni,ij,njk->nk", u_b, R, skew(m_tilde)) @ Jr
    J = np.zeros((m_tilde.shape[0] + 3, 4))
    J[:-3, :3] = J_phi
    J[:-3, 3] = np.cos(p[3])
    J[-3:, :3] = w_prior * np.eye(3)
    return J


def _right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): Exp(φ + dφ) ≈ Exp(φ)·Exp(J_r(φ) dφ)."""
    th = float(np.linalg.norm(phi))
    K = skew(phi)
    if th < 1e-6:
        return np.eye(3) - 0.5 * K
    return (np.eye(3) - (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * (K @ K))


def align_axes(m_tilde: np.ndarray, u_b: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Rotation R and dip δ so that (R m̃_t)ᵀ u_b,t = −sin δ (Kok et al. 2012, [inclination]).

    Args:
        m_tilde: (N, 3) ellipsoid-calibrated field D₀⁻¹(y − o₀) (unit norm, magnetometer axes);
            NaN rows are ignored.
        u_b: (N, 3) body "up" directions acc/‖acc‖ at low-acceleration samples (same rows).

    Returns:
        R: (3, 3) rotation from the magnetometer's to the inertial axes (m_b = R m̃; D = D₀Rᵀ).
        dip_rad: δ in rad (positive: field points down).
        residual_rms: RMS of the residual (R m̃)ᵀu + sin δ (dimensionless, ≈ cos of angle error).

    Raises:
        ValueError: fewer than 4 usable rows (callers check coverage first).
    """
    m_tilde, u_b = np.asarray(m_tilde, float), np.asarray(u_b, float)
    ok = np.all(np.isfinite(m_tilde), axis=1) & np.all(np.isfinite(u_b), axis=1)
    m_tilde, u_b = m_tilde[ok], u_b[ok]
    if m_tilde.shape[0] < 4:
        raise ValueError(f"align_axes: found {m_tilde.shape[0]} usable rows; expected at least 4")
    if m_tilde.shape[0] > MAX_ROWS:
        idx = np.linspace(0, m_tilde.shape[0] - 1, MAX_ROWS).round().astype(int)
        m_tilde, u_b = m_tilde[idx], u_b[idx]
    m_tilde = m_tilde / np.linalg.norm(m_tilde, axis=1, keepdims=True)
    u_b = u_b / np.linalg.norm(u_b, axis=1, keepdims=True)
    dip0 = float(np.arcsin(np.clip(-np.mean(np.sum(m_tilde * u_b, axis=1)), -1, 1)))
    w_prior = PRIOR_WEIGHT * np.sqrt(m_tilde.shape[0])
    sol = least_squares(_residuals, np.array([0.0, 0.0, 0.0, dip0]), jac=_jacobian,
                        args=(m_tilde, u_b, w_prior), loss="soft_l1", f_scale=0.05)
    R = expmap(sol.x[:3])
    dip = float(np.arctan2(np.sin(sol.x[3]), abs(np.cos(sol.x[3]))))   # fold into [−π/2, π/2]
    r = np.einsum("ij,nj,ni->n", R, m_tilde, u_b) + np.sin(dip)
    return R, dip, float(np.sqrt(np.mean(r ** 2)))


def undelay_magnetometer(t: np.ndarray, b_mag: np.ndarray, delay_s: float) -> np.ndarray:
    """The field on the gyro's time base: row i holds the sample read n = round(τ/Δt) rows later.

    A magnetometer that lags by τ reports at t_i what the body saw at t_i − τ; pairing each sample with
    the orientation at its own time makes a turning body look like a field error ≈ |ω|·τ (0.9° at
    100 °/s for BROAD's 9 ms). The shift is by whole samples: interpolating between samples would
    average their noise (and bias the noise estimate low); the remaining ≤ ½ sample is negligible.
    Rows shifted in from beyond the end are NaN (no sample), as are rows that had none.

    Args:
        t: (N,) s; b_mag: (N, 3) field, NaN rows = no sample; delay_s: τ from `estimate_mag_delay`.
    """
    b_mag = np.asarray(b_mag, float)
    n = int(np.round(delay_s / float(np.median(np.diff(t))))) if len(t) > 1 else 0
    return shift_rows(b_mag, n)


def shift_rows(rows: np.ndarray, n: int) -> np.ndarray:
    """out_i = rows_{i+n} (NaN where i + n is outside), (N, 3) → (N, 3); n of either sign."""
    out = np.full_like(rows, np.nan)
    if n == 0:
        out[:] = rows
    elif n > 0:
        out[:-n] = rows[n:]
    else:
        out[-n:] = rows[:n]
    return out
