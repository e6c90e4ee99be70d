"""Factors of the multi-IMU body estimator (after Kok, Hol & Schön, "An optimization-based approach to human
body motion capture using inertial sensors", IFAC 2014; numbered (B1)–(B5) here).

Variables (keys below): per sensor s and keyframe k the sensor pose nTs = (nRs, n_p_s) as a gtsam Pose3
X(s,k) and its velocity V(s,k); per sensor and bias segment m an `imuBias.ConstantBias` B(s,m) (random
walk between segments, BetweenFactorConstantBias; m = 0 only for a constant bias); per joint j and keyframe k the
joint centre J(j,k) in n (Point3); per (sensor, joint) pair a lever arm l = s_r (joint centre in the sensor
frame, Point3, constant over time).

    (B1) dynamics      ImuFactor(X(s,k), V(s,k), X(s,k+1), V(s,k+1), B(s,m(k))) from preintegrated gyr/acc
    (B2) joint         J(j,k) = nTs_P(k) · l_P  and  J(j,k) = nTs_C(k) · l_C   (both sensors meet at the joint)
    (B3) placement     l ~ N(l_nominal, σ_l² I)  (sensor approximately fixed on its segment)
    (B4) hinge         (nRs_P sRb_P a)ᵀ ⊥ … : the child's hinge axis stays on the parent's, 2-D residual
    (B5) magnetometer  b_mag ≈ F · nRsᵀ n_m(s)  (MagPoseFactorPose3, per-sensor field direction n_m(s))

(B2) uses gtsam's C++ `ReferenceFrameFactorPoint3Pose3(global_key, trans_key, local_key)`, whose semantics
are local = trans.transformFrom(global) (GTSAM_NOTES.md; checked numerically in tests/test_body_factors.py):
so the lever arm is the "global" key, the pose the "trans" key and the joint centre the "local" key.
(B4) is a Python CustomFactor (analytic Jacobians, tested against numerical derivatives).
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.geometry import expmap, logmap, skew

_STRIDE = 10_000_000          # key index = owner · _STRIDE + keyframe


def pose_key(s: int, k: int) -> int:
    """X(s,k): Pose3 nTs of sensor s at keyframe k."""
    return gtsam.symbol("x", s * _STRIDE + k)


def vel_key(s: int, k: int) -> int:
    """V(s,k): velocity of sensor s at keyframe k in n, m/s."""
    return gtsam.symbol("v", s * _STRIDE + k)


def bias_key(s: int, m: int = 0) -> int:
    """B(s,m): imuBias.ConstantBias (acc, gyro) of sensor s in bias segment m (random walk, see
    imugraph.graphs.body_model.bias_segments; m = 0 only when the bias is constant)."""
    return gtsam.symbol("b", s * _STRIDE + m)


def joint_key(j: int, k: int) -> int:
    """J(j,k): Point3 joint centre of joint j at keyframe k in n, m."""
    return gtsam.symbol("j", j * _STRIDE + k)


def lever_key(i: int) -> int:
    """L(i): Point3 lever arm i (joint centre in a sensor frame), m."""
    return gtsam.symbol("l", i)


def key_dim(key: int) -> int:
    """Tangent dimension of a body-graph key (from its character; a, o: imugraph.factors.body_axial; u, q, n:
    imugraph.graphs.body_chain; h, g: imugraph.factors.knee_sta)."""
    dims = {"x": 6, "v": 3, "b": 6, "j": 3, "l": 3, "a": 1, "o": 1, "u": 6, "q": 3, "n": 3, "h": 1, "g": 1}
    return dims[chr(gtsam.Symbol(key).chr())]


def joint_factors(j_key: int, pose_P: int, lever_P: int, pose_C: int, lever_C: int,
                  model: gtsam.noiseModel.Base) -> list:
    """(B2): J = nTs_P · l_P and J = nTs_C · l_C as two C++ factors (local = trans.transformFrom(global))."""
    return [gtsam.ReferenceFrameFactorPoint3Pose3(lever_P, pose_P, j_key, model),
            gtsam.ReferenceFrameFactorPoint3Pose3(lever_C, pose_C, j_key, model)]


def imu_params(g: float, sigma_gyr: np.ndarray, sigma_acc: np.ndarray, dt: float,
               integration_sigma: float = 1e-4) -> gtsam.PreintegrationParams:
    """Preintegration parameters for (B1); z-up navigation frame with gravity −g.

    The discrete per-sample standard deviations σ become continuous-time densities: Σ_c = σ² · dt.
    """
    p = gtsam.PreintegrationParams.MakeSharedU(float(g))
    p.setGyroscopeCovariance(np.diag(np.asarray(sigma_gyr, float) ** 2 * dt))
    p.setAccelerometerCovariance(np.diag(np.asarray(sigma_acc, float) ** 2 * dt))
    p.setIntegrationCovariance(np.eye(3) * integration_sigma**2)
    return p


def right_jacobian(theta: np.ndarray) -> np.ndarray:
    """(…, 3) → (…, 3, 3) right Jacobian of SO(3), Exp(θ + δ) ≈ Exp(θ) Exp(Jr(θ) δ):

        Jr(θ) = I − (1 − cos t)/t² [θ]× + (t − sin t)/t³ [θ]×²,   t = |θ|                            (P4)
    """
    theta = np.asarray(theta, float)
    t = np.linalg.norm(theta, axis=-1)[..., None, None]
    small = t < 1e-6
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t**2 / 120.0, (ts - np.sin(ts)) / ts**3)
    K = skew(theta)
    return np.eye(3) - a * K + b * (K @ K)


def exact_rotation_gyro(gyr: np.ndarray, dt: np.ndarray, kf: np.ndarray, b_gyr: np.ndarray,
                        max_angle: float = 2.8) -> np.ndarray:
    """Gyro samples that make gtsam's tangent-space preintegration reproduce the rotation exactly.

    gtsam (4.3, TangentPreintegration) integrates the preintegrated rotation θ = Log(ΔR) by one Euler step
    per sample, θ_{m+1} = θ_m + Jr(θ_m)⁻¹ (ω_m − b̂) dt_m: first order in |ω dt| (measured: 25 rad/s with
    the axis changing every 1/60 s sample, 1.7–2.6° off after 6 samples; errors shrink only ∝ 1/n with n
    sub-steps). Exact is ΔR_{m+1} = ΔR_m Exp((ω_m − b̂) dt_m). Feeding

        ω'_m = Jr(θ_m) (θ_{m+1} − θ_m)/dt_m + b̂,   θ_m = Log(ΔR_m) of the exact product,              (P5)

    makes gtsam's step land on the exact θ_{m+1}; its position/velocity step uses R(θ_m) = ΔR_m, i.e. the
    specific force of sample m held in the sensor frame at its start (the discrete model of
    imugraph.sim.body, P3). Where |θ| would pass `max_angle` (near π, where Log jumps) the raw samples are
    kept for the rest of that keyframe interval.

    Args:
        gyr: (N, 3) rad/s; dt: (N,) s; kf: keyframe sample indices; b_gyr: (3,) the preintegration's b̂.
    Returns:
        (N, 3) gyro samples to feed to `integrateMeasurement` (samples outside [kf[0], kf[-1]) unchanged).
    """
    gyr = np.asarray(gyr, float)
    out = gyr.copy()
    a, L = np.asarray(kf[:-1]), np.diff(kf)
    if a.size == 0:
        return out
    R = np.tile(np.eye(3), (a.size, 1, 1))
    theta = np.zeros((a.size, 3))
    ok = np.ones(a.size, bool)
    for m in range(int(L.max())):
        sel = np.flatnonzero(ok & (m < L))
        if sel.size == 0:
            break
        i = a[sel] + m
        R_next = R[sel] @ expmap((gyr[i] - b_gyr) * dt[i][:, None])
        th_next = logmap(R_next)
        good = np.linalg.norm(th_next, axis=1) < max_angle
        sel, i, R_next, th_next = sel[good], i[good], R_next[good], th_next[good]
        ok[np.setdiff1d(np.flatnonzero(ok & (m < L)), sel)] = False
        d = (th_next - theta[sel]) / dt[i][:, None]
        out[i] = np.einsum("kij,kj->ki", right_jacobian(theta[sel]), d) + b_gyr                  # (P5)
        R[sel], theta[sel] = R_next, th_next
    return out


def preintegrate(gyr: np.ndarray, acc: np.ndarray, dt: np.ndarray, kf: np.ndarray,
                 params: gtsam.PreintegrationParams, bias: gtsam.imuBias.ConstantBias,
                 exact_rotation: bool = True) -> list:
    """One PreintegratedImuMeasurements per keyframe interval [kf[i], kf[i+1]) (samples' own dt); with
    exact_rotation the gyro samples are first mapped by `exact_rotation_gyro` (P5)."""
    if exact_rotation:
        gyr = exact_rotation_gyro(gyr, dt, kf, np.asarray(bias.gyroscope(), float))
    out = []
    for a, b in zip(kf[:-1], kf[1:]):
        pim = gtsam.PreintegratedImuMeasurements(params, bias)
        for i in range(a, b):
            pim.integrateMeasurement(acc[i], gyr[i], float(dt[i]))
        out.append(pim)
    return out


def hinge_basis(s_axis: np.ndarray) -> np.ndarray:
    """(2, 3) two unit vectors orthogonal to the unit axis s_axis (rows)."""
    a = np.asarray(s_axis, float) / np.linalg.norm(s_axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u1 = np.cross(a, helper)
    u1 /= np.linalg.norm(u1)
    return np.stack([u1, np.cross(a, u1)])


def hinge_residual(nRs_P: np.ndarray, nRs_C: np.ndarray, s_U_P: np.ndarray, s_a_C: np.ndarray,
                   jacobians: bool = False):
    """(B4) e = U_P · (nRs_Pᵀ nRs_C s_a_C): the child's axis, seen from the parent sensor, has no
    component orthogonal to the parent's axis (rows U_P span that orthogonal plane).

    Right perturbations R ← R·Exp(δ): d(Rᵀm)/dδ = [Rᵀm]×, d(R a)/dδ = −R [a]×. Returns e (2,) and, with
    jacobians, (2, 3) blocks for δ_P and δ_C.
    """
    m = nRs_P.T @ (nRs_C @ s_a_C)
    e = s_U_P @ m
    if not jacobians:
        return e
    H_P = s_U_P @ skew(m)
    H_C = -s_U_P @ (nRs_P.T @ nRs_C) @ skew(s_a_C)
    return e, H_P, H_C


def hinge_factor(model: gtsam.noiseModel.Base, pose_P: int, pose_C: int, sRb_P: np.ndarray, sRb_C: np.ndarray,
                 b_axis: np.ndarray | None = None) -> gtsam.CustomFactor:
    """(B4) as a CustomFactor on two sensor poses, for a hinge about `b_axis` (segment frames; the lateral
    y axis for knee and elbow in the MVN neutral pose) with the sensor-to-segment rotations held fixed."""
    b_axis = np.array([0.0, 1.0, 0.0]) if b_axis is None else np.asarray(b_axis, float)
    s_U_P = hinge_basis(sRb_P @ b_axis)
    s_a_C = sRb_C @ b_axis
    zero = np.zeros((2, 3))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
        RP = values.atPose3(this.keys()[0]).rotation().matrix()
        RC = values.atPose3(this.keys()[1]).rotation().matrix()
        if H is None:
            return hinge_residual(RP, RC, s_U_P, s_a_C)
        e, HP, HC = hinge_residual(RP, RC, s_U_P, s_a_C, jacobians=True)
        H[0] = np.hstack([HP, zero])               # Pose3 tangent (ω, v): rotation first
        H[1] = np.hstack([HC, zero])
        return e

    return gtsam.CustomFactor(model, [pose_P, pose_C], error)


def mag_factor(pose: int, b_mag: np.ndarray, scale: float, n_dir: np.ndarray,
               model: gtsam.noiseModel.Base) -> gtsam.MagPoseFactorPose3:
    """(B5) b_mag = scale · nRsᵀ n_dir (+ 0 bias) on the sensor pose (C++)."""
    return gtsam.MagPoseFactorPose3(pose, np.asarray(b_mag, float), float(scale),
                                    np.asarray(n_dir, float) / np.linalg.norm(n_dir), np.zeros(3), model)


def yaw_information_prior(key: int, nTs: gtsam.Pose3, sigma_pos: float, sigma_yaw: float,
                          sigma_tilt: float) -> gtsam.PriorFactorPose3:
    """Gauge prior on a pose: position σ_pos, heading (rotation about n's z) σ_yaw, tilt σ_tilt.

    The Pose3 rotation error is in the sensor frame, δ_s; its navigation-frame part is nRs δ_s, so the
    rotation covariance is nRsᵀ diag(σ_tilt², σ_tilt², σ_yaw²) nRs (and the position error, also in the
    sensor frame, gets σ_pos isotropically).
    """
    R = nTs.rotation().matrix()
    cov = np.zeros((6, 6))
    cov[:3, :3] = R.T @ np.diag([sigma_tilt**2, sigma_tilt**2, sigma_yaw**2]) @ R
    cov[3:, 3:] = np.eye(3) * sigma_pos**2
    return gtsam.PriorFactorPose3(key, nTs, gtsam.noiseModel.Gaussian.Covariance(cov))
