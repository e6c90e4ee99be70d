"""The nav-field perturbation of the batch model (imugraph.factors.field) for ONE keyframe of a stream.

The batch path (imugraph.calibration.ml with Options.field_sigma) adds a per-keyframe nav-frame vector d_k
(unit-field units) to the Earth field, with a first-order Gauss–Markov prior (stationary std σ_d per nav
axis, correlation time τ_d):

    y_j = D ΔR_jᵀ R_kᵀ (n_mag(δ) + d_k) + o + e_j                                              (1)
    d_0 ~ N(0, σ_d²),  d_{k+1} = φ_k d_k + w_k,  φ_k = exp(−Δt_k/τ_d),  w_k ~ N(0, σ_d²(1 − φ_k²))   (2)

The stream averages the interval's calibrated field in keyframe k's frame, m̄_k = mean_j ΔR_j D⁻¹(y_j − o)
(full covariance Σ_k, as `StreamSmoother._mag_factor`), so (1) becomes one 3-row factor on (pose_k, d_k):

    e_k = R_kᵀ (n + d_k) − m̄_k,   ∂e/∂ω = [R_kᵀ(n + d_k)]×,   ∂e/∂d_k = R_kᵀ                      (3)

(right perturbation R_k Exp(ω), gtsam's Pose3 tangent [ω, v]: zero Jacobian in the position). gtsam's
Python wheel has no built-in factor of a rotation and a free nav vector without the pose's translation
(GTSAM_NOTES.md), so (3) is a `gtsam.CustomFactor` (tens of µs per linearisation, one per keyframe); (2) is
exactly linear: `LinearContainerFactor`s of `JacobianFactor`s, like the bounded-velocity prior.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from imugraph.factors.field import field_key, field_sigmas, field_steps  # noqa: F401 (re-exported)

__all__ = ["field_key", "field_mag_factor", "field_start_prior", "field_step_factor", "field_sigmas", "linearized_once"]

_ZERO3, _UNIT3 = np.zeros(3), gtsam.noiseModel.Unit.Create(3)


def field_mag_factor(pose_k: int, field_k: int, m_avg: np.ndarray, n_mag: np.ndarray, model) -> gtsam.CustomFactor:
    """Eq. (3): keyframe k's averaged calibrated field m̄_k against R_kᵀ(n + d_k); `model` holds Σ_k (robust or not)."""
    n, m = np.asarray(n_mag, float).copy(), np.asarray(m_avg, float).copy()

    def error(this, values, H):
        Rt = values.atPose3(pose_k).rotation().matrix().T
        x, y, z = b_field = Rt @ (n + values.atVector(field_k))        # R_kᵀ(n + d_k)
        if H is not None:
            # d(Exp(ω)ᵀ Rᵀ v)/dω = [Rᵀv]× (geometry.skew, written out: this runs ~20 times per update)
            H[0] = np.array([[0.0, -z, y, 0.0, 0.0, 0.0], [z, 0.0, -x, 0.0, 0.0, 0.0], [-y, x, 0.0, 0.0, 0.0, 0.0]])
            H[1] = Rt
        return b_field - m

    return gtsam.CustomFactor(model, [pose_k, field_k], error)


def field_start_prior(field_0: int, sigma_d) -> gtsam.PriorFactorVector:
    """d_0 ~ N(0, diag σ_d²), eq. (2)."""
    return gtsam.PriorFactorVector(field_0, _ZERO3, gtsam.noiseModel.Diagonal.Sigmas(field_sigmas(sigma_d)))


def field_step_factor(field_k: int, field_next: int, dt_k: float, sigma_d, tau_d: float) -> gtsam.LinearContainerFactor:
    """(d_{k+1} − φ_k d_k)/σ_w,k ~ N(0, I), φ_k = exp(−Δt_k/τ_d), σ_w,k = σ_d √(1 − φ_k²): eq. (2), exact.
    The coefficients of `imugraph.factors.field.field_steps` in scalar arithmetic (one interval per call:
    the array version's overhead was half of this function's time; tests/test_stream_field.py compares)."""
    from imugraph.graphs.stream_kernels import field_blocks, linear_step

    return linear_step(field_k, field_next, field_blocks(dt_k, field_sigmas(sigma_d), tau_d))


def linearized_once(factor, pose_k: int, pose: gtsam.Pose3, field_k: int, d: np.ndarray) -> gtsam.LinearContainerFactor:
    """`factor` (eq. 3) linearised at (pose, d) and held as a C++ LinearContainerFactor (first order about that
    point; robust weight frozen there).

    Why: gtsam's IncrementalFixedLagSmoother re-linearises EVERY factor of the window at every update here
    (gravity and the bias segment sit in every clique, so > 65 % of the variables are re-eliminated and iSAM2
    takes its batch path), and each Python call then receives a copy of the linearisation point: measured on
    BROAD 01 (60 s, lag 2 s) 35.6× real time in CPU time without the perturbation, 31.2× with its variables
    and C++ factors, 16.2× with this CustomFactor in the window. The point is keyframe k's estimate when its
    interval closes (k already had one update); what is neglected is second order in the later correction δ
    (|e| error ≤ |δ|²/2: 1.5e-4 of the unit field at 1°, against a magnetometer σ of ≈ 0.01)."""
    lin = gtsam.Values()
    lin.insert(pose_k, pose)
    lin.insert(field_k, np.asarray(d, float))
    return gtsam.LinearContainerFactor(factor.linearize(lin), lin)
