"""The normal equations of the joint gyro fit (effects/joint.py (J1)), assembled without the big matrices.

Same numbers as stacking the whitened rows into a sparse keyframe block Jw (3M × 3K, six non-zeros per
row) and a dense block Gd (3M × C: the effect's, the bias' and the magnetometer calibration's columns)
and forming JwᵀJw, JwᵀGd, Gdᵀ[Gd y], Jwᵀy (issue 5, H7: that assembly was most of the joint fit's CPU).
Here every sample j contributes outer products of its own rows (Jc_j: 3 × 6 on (w_k, w_{k+1}), G_j:
3 × C, y_j: 3), summed per keyframe interval before they are placed:

    JwᵀJw = Σ_k P_kᵀ (Σ_{j ∈ k} Jc_jᵀ Jc_j) P_k,    JwᵀGd = Σ_k P_kᵀ Σ_{j ∈ k} Jc_jᵀ G_j,    GdᵀGd = Σ_j G_jᵀ G_j
                                                                                                   (N1)
(P_k: the 6 × 3K selection of w_k, w_{k+1}; exact algebra, only the order of the floating-point sums
differs). The gyro change columns (J3) of C changes are computed at once (`gyro_changes`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from imugraph.diagnose.effects.trajectory import interval_index
from imugraph.geometry import skew


def gyro_changes(fit, d_omega: np.ndarray) -> dict:
    """(J3) of effects/joint.py for C gyro changes Δω (C, N, 3) at once, keyframes fixed:

        φ_j = Σ_{i=s_k}^{j−1} R_i Δω_i Δt_i,   v_j = φ_j − u_j φ_{s_{k+1}}          (nav frame)        (J3)
        acc_j += (R_jᵀ v_j) × (R_jᵀ g_n),  mag_j += D ((R_jᵀ v_j) × (R_jᵀ n)),  gyr_j += R_jᵀ φ_{s_{k+1}} / T_k

    (D, n: the fit's calibration). Returns channel → (N, 3, C) residual columns."""
    d = np.ascontiguousarray(np.moveaxis(np.nan_to_num(np.asarray(d_omega, float)), 0, 2))   # (N, 3, C)
    n = fit.n
    kf = np.asarray(fit.keyframe_samples, int)
    inc = (fit.nRb @ d) * fit.session.dt[:, None, None]                       # R_i Δω_i Δt_i
    Cs = np.concatenate([np.zeros((1,) + d.shape[1:]), np.cumsum(inc, axis=0)])
    k, s_k = interval_index(fit)
    s_next = kf[np.minimum(k + 1, len(kf) - 1)]
    has_next = (k < len(kf) - 1)[:, None, None]
    phi = Cs[:n] - Cs[s_k]
    Phi = np.where(has_next, Cs[s_next] - Cs[s_k], 0.0)
    u = np.where(has_next[:, 0, 0], (np.arange(n) - s_k) / np.maximum(s_next - s_k, 1), 0.0)
    T = np.where(has_next[:, 0, 0], fit.session.t[s_next] - fit.session.t[s_k], 1.0)
    bRn = np.transpose(fit.nRb, (0, 2, 1))
    dth = bRn @ (phi - u[:, None, None] * Phi)
    # x × h = −[h]× x
    acc = -skew(bRn @ np.array([0.0, 0.0, fit.g])) @ dth
    mag = (np.asarray(fit.calibration.D, float) @ -skew(bRn @ np.asarray(fit.calibration.n_mag, float))) @ dth
    return {"gyr": (bRn @ Phi) / T[:, None, None], "acc": acc, "mag": mag}


def nuisance_columns(cur) -> np.ndarray:
    """(N, 3, 13) magnetometer rows' columns of its calibration change q = (ΔD row-major, Δo, Δdip) at the
    moved calibration `cur.info["mag_calibration"]` (r_mag = y − D R_jᵀ n(dip) − o); the other channels'
    are zero."""
    m = cur.info["mag_calibration"]
    D, dip = m["D"], m["dip_rad"]
    bRn = np.transpose(cur.nRb, (0, 2, 1))
    n_b = bRn @ m["n_nav"]
    out = np.zeros((cur.n, 3, 13))
    for a in range(3):
        out[:, a, 3 * a:3 * a + 3] = -n_b                                  # ∂r_mag,a/∂D_ab = −n_b,b
        out[:, a, 9 + a] = -1.0                                            # ∂r_mag/∂o_a
    out[:, :, 12] = -(bRn @ np.array([-np.sin(dip), 0.0, -np.cos(dip)])) @ D.T   # ∂r_mag/∂dip
    return out


def _outer(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(m, a, b) A_jᵀ B_j for A (m, 3, a), B (m, 3, b)."""
    return np.transpose(A, (0, 2, 1)) @ B


def _per_interval(x: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sums of x (m, ...) over runs of equal k (k non-decreasing): (groups, ...) and their k."""
    start = np.flatnonzero(np.concatenate([[True], k[1:] != k[:-1]]))
    return np.add.reduceat(x, start, axis=0), k[start]


def _pair_columns(k: np.ndarray, K: int) -> np.ndarray:
    """(len(k), 6) columns of (w_k, w_{k+1}) in the 3K keyframe vector (k + 1 → K − 1 at the last keyframe)."""
    return np.concatenate([3 * k[:, None] + np.arange(3), 3 * np.minimum(k + 1, K - 1)[:, None] + np.arange(3)], axis=1)


def normal_equations(J: dict, k: np.ndarray, cols: dict, rows: dict, K: int, C: int) -> tuple:
    """(N1) for the whitened, Huber-weighted rows of each channel.

    J: channel → (m, 3, 6) keyframe block of the rows' samples; cols: channel → (m, 3, C_c) dense columns
    (C_c ≤ C: a channel's missing trailing columns are zero, the magnetometer calibration's on gyr and
    acc); rows: channel → (idx (m,) sample indices ascending, y (m, 3) right-hand side). k: (N,) interval
    of each sample (its keyframes k and min(k + 1, K − 1), as `joint._keyframe_jacobian`). Returns (Hww (3K × 3K sparse CSC), Hwp (3K, C), gw (3K,),
    GG (C, C), gp (C,)), C: the number of dense columns."""
    HB = np.zeros((K, 6, 6))
    Hwp, gw = np.zeros((3 * K, C)), np.zeros(3 * K)
    GG, gp = np.zeros((C, C)), np.zeros(C)
    for c, Jc in J.items():
        idx, y = rows[c]
        Gc = cols[c]
        w = Gc.shape[2]
        G2 = Gc.reshape(-1, w)
        GG[:w, :w] += G2.T @ G2                                            # GdᵀGd
        gp[:w] += G2.T @ y.reshape(-1)
        kc = k[idx]
        JJ, kg = _per_interval(_outer(Jc, Jc), kc)
        np.add.at(HB, kg, JJ)
        # Jw of this channel as CSR (six non-zeros per row, on w_k and w_{k+1}): JwᵀGd, Jwᵀy
        sel = _pair_columns(kc, K)
        m = len(idx)
        Jw = sp.csr_matrix((Jc.reshape(-1), np.repeat(sel[:, None, :], 3, axis=1).reshape(-1),
                            np.arange(0, 18 * m + 1, 6)), shape=(3 * m, 3 * K))
        JwT = Jw.T
        Hwp[:, :w] += JwT @ G2
        gw += JwT @ y.reshape(-1)
    # place the 6 × 6 blocks on (w_k, w_{k+1}) (k + 1 → K − 1 at the end, where the block's second half is 0)
    sel = _pair_columns(np.arange(K), K)                                                   # (K, 6)
    r = np.repeat(sel[:, :, None], 6, axis=2).reshape(-1)
    cidx = np.repeat(sel[:, None, :], 6, axis=1).reshape(-1)
    Hww = sp.csc_matrix((HB.reshape(-1), (r, cidx)), shape=(3 * K, 3 * K))    # duplicates summed
    return Hww, Hwp, gw, GG, gp
