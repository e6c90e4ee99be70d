"""Magnetometer calibration factor (Kok & Schön, IEEE Sensors J. 2016, eq. 6; Kok et al. FUSION 2012).

Measurement model for sample j attached to keyframe k through the preintegrated gyro rotation ΔR_j
(nRb_j = R_k · ΔR_j):

    y_j = D · ΔR_jᵀ · R_kᵀ · n_mag(δ) + o + e_j,      n_mag(δ) = [cos δ, 0, −sin δ]ᵀ,   e_j ~ N(0, Σ_m)

Residual e_j = h_j − y_j with h_j = D u_j + o, v_k = R_kᵀ n_mag, u_j = ΔR_jᵀ v_k. Jacobians (right
perturbation R_k ← R_k·Exp(ξ), so ∂v_k/∂ξ = [v_k]×):

    ∂e_j/∂ξ   = D ΔR_jᵀ [v_k]×
    ∂e_j/∂d   = I₃ ⊗ u_jᵀ            (d = vec D, row-major)
    ∂e_j/∂o   = I₃
    ∂e_j/∂δ   = D ΔR_jᵀ R_kᵀ n_mag'(δ),   n_mag'(δ) = [−sin δ, 0, −cos δ]ᵀ
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors.theta import INDEX_DIP, SLICE_D, SLICE_O, THETA_DIM, unpack_theta
from imugraph.geometry import skew


def n_mag(dip_rad: float) -> np.ndarray:
    return np.array([np.cos(dip_rad), 0.0, -np.sin(dip_rad)])


def magnetometer_model(kRb: np.ndarray, nRk: np.ndarray, theta: np.ndarray, b_mag: np.ndarray):
    """Residuals and Jacobians of M magnetometer samples.

    Args:
        kRb: (M, 3, 3) ΔR_j, rotation of sample j's body frame into its keyframe's body frame.
        nRk: (M, 3, 3) keyframe orientation R_k for each sample (repeated rows are fine).
        theta: (13,) calibration (vec D, o, δ).
        b_mag: (M, 3) measured field.

    Returns:
        e (M, 3) residual h − y; J_rot (M, 3, 3) w.r.t. the keyframe rotation; J_theta (M, 3, 13).
    """
    D, o, dip = unpack_theta(theta)
    v = np.einsum("mji,j->mi", nRk, n_mag(dip))                # v = R_kᵀ n
    dv = np.einsum("mji,j->mi", nRk, np.array([-np.sin(dip), 0.0, -np.cos(dip)]))
    bRk = np.transpose(kRb, (0, 2, 1))
    u = np.einsum("mij,mj->mi", bRk, v)                         # u = ΔRᵀ v
    DbRk = D @ bRk                                              # (M,3,3) D ΔRᵀ
    e = u @ D.T + o - b_mag
    J_rot = DbRk @ skew(v)
    m = u.shape[0]
    J_theta = np.zeros((m, 3, THETA_DIM))
    for i in range(3):
        J_theta[:, i, 3 * i:3 * i + 3] = u
    J_theta[:, :, SLICE_O] = np.eye(3)
    J_theta[:, :, INDEX_DIP] = np.einsum("mij,mj->mi", DbRk, dv)
    return e, J_rot, J_theta


def _rotate_back(kRb: np.ndarray, x: np.ndarray) -> np.ndarray:
    """ΔR_jᵀ x_j for (M, 3, 3) and (M, 3): three broadcast products (faster than a batched matmul)."""
    return kRb[:, 0, :] * x[:, :1] + kRb[:, 1, :] * x[:, 1:2] + kRb[:, 2, :] * x[:, 2:]


def _nav_field(nRk: np.ndarray, dip: float, n_offset: np.ndarray | None) -> np.ndarray:
    """v_k = R_kᵀ (n_mag(δ) + d_k) (K, 3): the field in each keyframe's body axes, with the optional
    per-keyframe nav-frame field perturbation d_k (imugraph.factors.field)."""
    n = n_mag(dip)
    if n_offset is None:
        return np.einsum("kji,j->ki", nRk, n)
    return np.einsum("kji,kj->ki", nRk, n + np.asarray(n_offset, float))


def magnetometer_residual(kRb: np.ndarray, kf: np.ndarray, nRk: np.ndarray, theta: np.ndarray,
                          b_mag: np.ndarray, n_offset: np.ndarray | None = None) -> np.ndarray:
    """Residuals e_j = D ΔR_jᵀ R_kᵀ (n_mag(δ) + d_k) + o − y_j (M, 3) only, keyframe rotations given per
    keyframe.

    Args:
        kRb: (M, 3, 3) ΔR_j; kf: (M,) keyframe of each sample; nRk: (K, 3, 3) keyframe orientations;
        theta: (13,) calibration; b_mag: (M, 3) measured field; n_offset: (K, 3) nav-frame field
        perturbation d_k per keyframe (unit-field units), None: zero.
    """
    D, o, dip = unpack_theta(theta)
    v = _nav_field(nRk, dip, n_offset)                          # v_k = R_kᵀ (n + d_k)   (K, 3)
    u = _rotate_back(kRb, v[kf])                                # u_j = ΔR_jᵀ v_k
    return u @ D.T + o - b_mag


def magnetometer_rows(kRb: np.ndarray, kf: np.ndarray, nRk: np.ndarray, theta: np.ndarray,
                      b_mag: np.ndarray, n_offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unwhitened linearisation of M samples in a form whose per-keyframe Gram is cheap to accumulate.

    Returns X (M, 3, 3 + 13 + 1) with columns [D ΔR_jᵀ | ∂e_j/∂θ | e_j] and V (K, 3, 3) = [v_k]×,
    v_k = R_kᵀ n_mag: the rotation Jacobian of sample j is X[j, :, :3] · V[kf_j] (eq. above, ∂e/∂ξ =
    D ΔR_jᵀ [v_k]×), factored so that the 3×3 product is applied once per keyframe, not per sample.

    With a field perturbation d_k (n_offset), v_k = R_kᵀ (n_mag + d_k) and ∂e_j/∂d_k = D ΔR_jᵀ R_kᵀ, i.e.
    X[j, :, :3] · R_kᵀ (the same left factor as the rotation Jacobian).

    Args as `magnetometer_residual`.
    """
    D, o, dip = unpack_theta(theta)
    v = _nav_field(nRk, dip, n_offset)                          # v_k = R_kᵀ (n + d_k)
    dv = np.einsum("kji,j->ki", nRk, np.array([-np.sin(dip), 0.0, -np.cos(dip)]))   # R_kᵀ n'(δ)
    m = len(kf)
    u = _rotate_back(kRb, v[kf])                                # u_j = ΔR_jᵀ v_k
    z = _rotate_back(kRb, dv[kf])                               # z_j = ΔR_jᵀ R_kᵀ n'(δ)
    X = np.empty((m, 3, 3 + THETA_DIM + 1))
    X[:, :, :3] = (kRb.reshape(-1, 3) @ D.T).reshape(m, 3, 3).transpose(0, 2, 1)   # D ΔR_jᵀ
    X[:, :, 3:3 + SLICE_O.stop] = 0.0
    for i in range(3):
        X[:, i, 3 + 3 * i:6 + 3 * i] = u                        # ∂e/∂d = I₃ ⊗ u_jᵀ
        X[:, i, 3 + SLICE_O.start + i] = 1.0                    # ∂e/∂o = I₃
    X[:, :, 3 + INDEX_DIP] = z @ D.T                            # ∂e/∂δ = D ΔR_jᵀ R_kᵀ n'(δ)
    X[:, :, -1] = u @ D.T + o - b_mag                           # e_j
    return X, skew(v)


def magnetometer_factor(key_rot: int, key_theta: int, kRb: np.ndarray, b_mag: np.ndarray,
                        sigma: np.ndarray) -> gtsam.CustomFactor:
    """A CustomFactor on (R_k, θ) for K magnetometer samples of one keyframe (batched: 3K rows).

    Args:
        kRb: (K, 3, 3) ΔR_j of each sample; b_mag: (K, 3); sigma: (3,) per-axis std (magnetometer unit).
    """
    kRb = np.asarray(kRb, float).copy()
    b_mag = np.asarray(b_mag, float).copy()
    model = gtsam.noiseModel.Diagonal.Sigmas(np.tile(np.asarray(sigma, float), len(b_mag)))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H):
        nRk = values.atRot3(this.keys()[0]).matrix()
        theta = values.atVector(this.keys()[1])
        e, J_rot, J_theta = magnetometer_model(kRb, np.broadcast_to(nRk, kRb.shape), theta, b_mag)
        if H is not None:
            H[0] = J_rot.reshape(-1, 3)
            H[1] = J_theta.reshape(-1, THETA_DIM)
        return e.reshape(-1)

    return gtsam.CustomFactor(model, [key_rot, key_theta], error)


__all__ = ["magnetometer_model", "magnetometer_residual", "magnetometer_rows", "magnetometer_factor", "n_mag",
           "SLICE_D"]
