"""Accelerometer factor: gravity direction seen in the body frame (Kok & Schön 2016, eq. 4).

For sample j attached to keyframe k through ΔR_j (nRb_j = R_k ΔR_j), with linear acceleration
treated as noise (robust kernel optional, see imugraph.factors.robust):

    a_j = −bRn n_grav + e_j = g · ΔR_jᵀ R_kᵀ e_z + e_j,     n_grav = [0, 0, −g]ᵀ,  e_j ~ N(0, Σ_a)

Residual e_j = g ΔR_jᵀ w_k − a_j with w_k = R_kᵀ e_z; Jacobian (right perturbation of R_k):

    ∂e_j/∂ξ = g ΔR_jᵀ [w_k]×
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.geometry import skew

E_UP = np.array([0.0, 0.0, 1.0])


def accelerometer_model(kRb: np.ndarray, nRk: np.ndarray, b_acc: np.ndarray, g: float):
    """Residuals (M, 3) and Jacobians (M, 3, 3) w.r.t. the keyframe rotation for M samples.

    Args:
        kRb: (M, 3, 3) ΔR_j; nRk: (M, 3, 3) keyframe orientation per sample; b_acc: (M, 3) m/s²;
        g: gravity magnitude m/s².
    """
    w = nRk[:, 2, :]                                   # R_kᵀ e_z = third row of R_k
    bRk = np.transpose(kRb, (0, 2, 1))
    e = g * np.einsum("mij,mj->mi", bRk, w) - b_acc
    J_rot = g * (bRk @ skew(w))
    return e, J_rot


def accelerometer_residual(kRb: np.ndarray, kf: np.ndarray, nRk: np.ndarray, b_acc: np.ndarray,
                           g: float) -> np.ndarray:
    """Residuals e_j = g ΔR_jᵀ R_kᵀ e_z − a_j (M, 3), keyframe rotations nRk (K, 3, 3) indexed by kf (M,)."""
    w = nRk[kf, 2, :]                                  # w_k = R_kᵀ e_z per sample
    return g * (kRb[:, 0, :] * w[:, :1] + kRb[:, 1, :] * w[:, 1:2] + kRb[:, 2, :] * w[:, 2:]) - b_acc


def accelerometer_rows(kRb: np.ndarray, kf: np.ndarray, nRk: np.ndarray, b_acc: np.ndarray,
                       g: float) -> tuple[np.ndarray, np.ndarray]:
    """X (M, 3, 4) with columns [g ΔR_jᵀ | e_j] and W (K, 3, 3) = [w_k]×: ∂e_j/∂ξ = X[j, :, :3] · W[kf_j]."""
    w = nRk[:, 2, :]                                   # w_k = R_kᵀ e_z
    m = len(kf)
    X = np.empty((m, 3, 4))
    X[:, :, :3] = g * kRb.transpose(0, 2, 1)
    X[:, :, 3] = accelerometer_residual(kRb, kf, nRk, b_acc, g)
    return X, skew(w)


def accelerometer_factor(key_rot: int, kRb: np.ndarray, b_acc: np.ndarray, sigma: np.ndarray,
                         g: float, robust: float | None = None) -> gtsam.CustomFactor:
    """A CustomFactor on R_k for K accelerometer samples of one keyframe (3K rows).

    Args:
        kRb: (K, 3, 3); b_acc: (K, 3) m/s²; sigma: (3,) m/s²; g: m/s²;
        robust: optional Huber threshold (whitened units) applied by GTSAM to the whole batch.
    """
    kRb = np.asarray(kRb, float).copy()
    b_acc = np.asarray(b_acc, float).copy()
    model = gtsam.noiseModel.Diagonal.Sigmas(np.tile(np.asarray(sigma, float), len(b_acc)))
    if robust is not None:
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust), model)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H):
        nRk = values.atRot3(this.keys()[0]).matrix()
        e, J_rot = accelerometer_model(kRb, np.broadcast_to(nRk, kRb.shape), b_acc, g)
        if H is not None:
            H[0] = J_rot.reshape(-1, 3)
        return e.reshape(-1)

    return gtsam.CustomFactor(model, [key_rot], error)
