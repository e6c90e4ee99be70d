"""Soft sensor-to-segment rotation about a segment's long axis (soft-tissue artefact), and the hinge with it.

Kok, Hol & Schön (IFAC 2014) treat each sensor's pose on its segment as approximately constant (soft
factors). The part of the soft-tissue artefact (STA) that the joints cannot see is the sensor turning about
the segment's long axis â (the line through the segment's two joint centres: turning about it moves
neither joint centre, so the joint factors (B2) are blind to it; see benchmarks/body_walk_diagnosis.py).
Here that rotation varies over time,

    bRs(k) = Exp(θ_k â) · bRs0,    θ_k = c + φ_k                                                    (S1)

with bRs0 the N-pose sensor-to-segment rotation, c a constant axial offset (the N-pose assumption "segments
world-aligned" says nothing about each leg's axial rotation in the stance) and φ_k a zero-mean first-order
Gauss–Markov process of standard deviation σ and correlation time τ:

    φ_0 ~ N(0, σ²),   φ_k − ρ_k φ_{k−1} ~ N(0, σ² (1 − ρ_k²)),   ρ_k = exp(−(t_k − t_{k−1})/τ)       (S2)

(the discrete process has stationary variance σ² whatever the keyframe spacing). The segment follows as
nRb = nRs bRs(k)ᵀ = nRs bRs0ᵀ Exp(−θ_k â). θ enters only factors that look at the SEGMENT orientation: the
hinge (B4) between a parent P and a child C with lateral axis y (segment frames):

    e = E · Exp(θ_P â_P) bRs0_P · nRs_Pᵀ nRs_C · bRs0_Cᵀ Exp(−θ_C â_C) y,    E = [x̂ᵀ; ẑᵀ]            (S3)

(the child's hinge axis, seen in the parent segment frame, has no x or z component), θ_P = 0 or θ_C = 0 for
a side without the soft rotation. With s_U_P = E Exp(θ_P â_P) bRs0_P and s_a_C = bRs0_Cᵀ Exp(−θ_C â_C) y
(S3) is imugraph.factors.body.hinge_residual, whose pose Jacobians are reused; d Exp(θ â)/dθ = [â]× Exp(θ â):

    ∂e/∂θ_P = E [â_P]× Exp(θ_P â_P) bRs0_P m,   m = nRs_Pᵀ nRs_C s_a_C
    ∂e/∂θ_C = −s_U_P nRs_Pᵀ nRs_C bRs0_Cᵀ [â_C]× Exp(−θ_C â_C) y                                  (S4)

Keys: A(s,k) the Vector1 φ of sensor s at keyframe k, O(s) the Vector1 offset c of sensor s.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors.body import _STRIDE, hinge_residual
from imugraph.geometry import expmap, skew

E_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])      # rows x̂, ẑ: orthogonal to the hinge axis y (S3)
Y = np.array([0.0, 1.0, 0.0])


def axial_key(s: int, k: int) -> int:
    """A(s,k): Vector1 φ (rad) of sensor s at keyframe k (S1)."""
    return gtsam.symbol("a", s * _STRIDE + k)


def axial_offset_key(s: int) -> int:
    """O(s): Vector1 constant axial offset c (rad) of sensor s (S1)."""
    return gtsam.symbol("o", s)


def axial_hinge_residual(nRs_P: np.ndarray, nRs_C: np.ndarray, bRs0_P: np.ndarray, bRs0_C: np.ndarray,
                         a_P: np.ndarray, a_C: np.ndarray, th_P: float, th_C: float, jacobians: bool = False):
    """(S3) e (2,); with jacobians also (2, 3) blocks for δ_P, δ_C (right rotation perturbations of the
    sensor rotations) and (2,) derivatives by θ_P and θ_C (S4)."""
    A_P, A_C = expmap(th_P * np.asarray(a_P, float)), expmap(-th_C * np.asarray(a_C, float))
    s_U_P = E_Y @ A_P @ bRs0_P
    s_a_C = bRs0_C.T @ (A_C @ Y)
    if not jacobians:
        return hinge_residual(nRs_P, nRs_C, s_U_P, s_a_C)
    e, H_P, H_C = hinge_residual(nRs_P, nRs_C, s_U_P, s_a_C, jacobians=True)
    m = nRs_P.T @ (nRs_C @ s_a_C)
    d_P = E_Y @ skew(a_P) @ A_P @ bRs0_P @ m                                            # (S4)
    d_C = -s_U_P @ (nRs_P.T @ nRs_C) @ bRs0_C.T @ (skew(a_C) @ (A_C @ Y))
    return e, H_P, H_C, d_P, d_C


def axial_hinge_factor(model: gtsam.noiseModel.Base, pose_P: int, pose_C: int, bRs0_P: np.ndarray,
                       bRs0_C: np.ndarray, a_P: np.ndarray, a_C: np.ndarray, theta_P: tuple = (),
                       theta_C: tuple = ()) -> gtsam.CustomFactor:
    """(S3) as a CustomFactor on the two sensor poses and the Vector1 keys whose sum is θ_P (`theta_P`, e.g.
    (A(P,k), O(P))) and θ_C (`theta_C`); an empty tuple holds that side's θ at 0 (a rigid sensor)."""
    keys = [pose_P, pose_C] + list(theta_P) + list(theta_C)
    nP = len(theta_P)
    bRs0_P, bRs0_C = np.asarray(bRs0_P, float), np.asarray(bRs0_C, float)
    a_P, a_C = np.asarray(a_P, float), np.asarray(a_C, float)
    zero = np.zeros((2, 3))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
        ks = this.keys()
        RP = values.atPose3(ks[0]).rotation().matrix()
        RC = values.atPose3(ks[1]).rotation().matrix()
        th = [float(values.atVector(k)[0]) for k in ks[2:]]
        th_P, th_C = sum(th[:nP]), sum(th[nP:])
        if H is None:
            return axial_hinge_residual(RP, RC, bRs0_P, bRs0_C, a_P, a_C, th_P, th_C)
        e, HP, HC, dP, dC = axial_hinge_residual(RP, RC, bRs0_P, bRs0_C, a_P, a_C, th_P, th_C, jacobians=True)
        H[0] = np.hstack([HP, zero])               # Pose3 tangent (ω, v): rotation first
        H[1] = np.hstack([HC, zero])
        for i in range(len(ks) - 2):
            H[2 + i] = (dP if i < nP else dC).reshape(2, 1)
        return e

    return gtsam.CustomFactor(model, keys, error)


def gauss_markov_link(key_prev: int, key: int, dt: float, sigma: float, tau: float) -> gtsam.CustomFactor:
    """(S2) φ_k − ρ φ_{k−1} ~ N(0, σ²(1 − ρ²)), ρ = exp(−dt/τ), on two Vector1 keys."""
    rho = float(np.exp(-float(dt) / float(tau)))
    model = gtsam.noiseModel.Isotropic.Sigma(1, float(sigma) * np.sqrt(max(1.0 - rho**2, 1e-12)))
    J_prev, J_this = np.array([[-rho]]), np.array([[1.0]])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
        ks = this.keys()
        e = values.atVector(ks[1]) - rho * values.atVector(ks[0])
        if H is not None:
            H[0], H[1] = J_prev, J_this
        return e

    return gtsam.CustomFactor(model, [key_prev, key], error)


def scalar_prior(key: int, sigma: float) -> gtsam.PriorFactorVector:
    """Zero-mean prior N(0, σ²) on a Vector1 key (φ_0 of (S2), the offset c)."""
    return gtsam.PriorFactorVector(key, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, float(sigma)))


def long_axis(skel, name: str) -> np.ndarray:
    """Unit long axis â of segment `name` in its own frame: from its proximal joint (origin) to its end."""
    a = np.asarray(skel.ends[skel.index(name)], float)
    return a / np.linalg.norm(a)
