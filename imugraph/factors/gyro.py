"""Gyroscope preintegration between keyframes (Forster et al. TRO 2017, rotation part), vectorised.

Gyro model (DESIGN.md): b_gyr = ω + δ_ω + e. Between keyframe samples s_k and s_{k+1} the measured rates
are integrated with the bias estimate b̂:

    ΔR_{k,j+1} = ΔR_{k,j} · Exp((ω_j − b̂) Δt_j)                                 (rotation, eq. 35)
    ∂ΔR/∂b    ← Exp(θ_j)ᵀ ∂ΔR/∂b − J_r(θ_j) Δt_j,     θ_j = (ω_j − b̂) Δt_j       (bias Jacobian, eq. 44)
    Σ_ΔR      ← Exp(θ_j)ᵀ Σ_ΔR Exp(θ_j) + (σ_d² + κ²|ω_j|²) Δt_j² I            (GTSAM's convention)

σ_d is the white noise measured at rest; κ|ω| adds the error that grows with the rate (scale-factor and
axis-misalignment uncertainty of a MEMS gyro, κ ≈ 1 %): without it a chain weighted by rest noise alone
is far too stiff in motion (measured on BROAD trial 01: 4.4° → 1.5° RMS with a 5× looser gyro).

The same recursion gives the intra-keyframe rotations kRb_j = ΔR_{k,j} that attach every accelerometer
and magnetometer sample to its keyframe. The results feed GTSAM's `PreintegratedAhrsMeasurements`
(full constructor) and C++ `AHRSFactor`, so no per-sample Python call into GTSAM is made.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph.factors.gaps import GAP_RATE_WALK, gap_steps, gap_variance, has_gap, keyframe_gap_step
from imugraph.geometry import skew


def right_jacobian(theta: np.ndarray) -> np.ndarray:
    """SO(3) right Jacobian J_r(θ), (…, 3) → (…, 3, 3)."""
    t = np.linalg.norm(theta, axis=-1)[..., None, None]
    K = skew(theta)
    small = t < 1e-6
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t**2 / 120.0, (ts - np.sin(ts)) / ts**3)
    return np.eye(3) - a * K + b * (K @ K)


def exp_and_right_jacobian(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exp(θ) and J_r(θ) for (…, 3) rotation vectors, with [θ]×² = θθᵀ − |θ|² I written out:

        Exp(θ) = cos|θ| I + (sin|θ|/|θ|) [θ]× + ((1 − cos|θ|)/|θ|²) θθᵀ                   (Rodrigues)
        J_r(θ) = I − ((1 − cos|θ|)/|θ|²) [θ]× + ((|θ| − sin|θ|)/|θ|³) (θθᵀ − |θ|² I)
    (the same series as geometry.expmap and right_jacobian near 0; elementwise, no 3×3 products).
    """
    theta = np.asarray(theta, float)
    shape = theta.shape[:-1]
    th = theta.reshape(-1, 3)
    t2 = np.einsum("mi,mi->m", th, th)
    t = np.sqrt(t2)
    small_e, small_j = t < 1e-8, t < 1e-6
    ts = np.where(small_e, 1.0, t)
    sin, cos = np.sin(ts), np.cos(ts)
    a_e = np.where(small_e, 1.0 - t2 / 6.0, sin / ts)
    b_e = np.where(small_e, 0.5 - t2 / 24.0, (1.0 - cos) / ts**2)
    a_j = np.where(small_j, 0.5 - t2 / 24.0, (1.0 - cos) / ts**2)
    b_j = np.where(small_j, 1.0 / 6.0 - t2 / 120.0, (ts - sin) / ts**3)
    outer = (th[:, :, None] * th[:, None, :]).reshape(-1, 9)
    R = b_e[:, None] * outer
    J = b_j[:, None] * outer
    R[:, _DIAG] += (1.0 - b_e * t2)[:, None]
    J[:, _DIAG] += (1.0 - b_j * t2)[:, None]
    w = th[:, _SKEW_SRC]                      # [θ]× entries (0,1), (1,2), (2,0) = −θz, −θx, −θy
    R[:, _SKEW_NEG] -= a_e[:, None] * w; R[:, _SKEW_POS] += a_e[:, None] * w
    J[:, _SKEW_NEG] += a_j[:, None] * w; J[:, _SKEW_POS] -= a_j[:, None] * w
    return R.reshape(shape + (3, 3)), J.reshape(shape + (3, 3))


_DIAG = [0, 4, 8]                  # flat indices of a 3×3 matrix: diagonal,
_SKEW_NEG = [1, 5, 6]              # (0,1) (1,2) (2,0),
_SKEW_POS = [3, 7, 2]              # (1,0) (2,1) (0,2),
_SKEW_SRC = [2, 0, 1]              # and the θ component each holds


def keyframe_layout(n: int, stride: int, dt: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe sample indices (K,) every `stride` samples (the last sample is always one), and the
    keyframe each sample is attached to (N,): sample i belongs to the last keyframe at or before it.

    dt: (N,) time steps; where given, the first sample after a gap longer than gaps.KEYFRAME_GAP_S (samples
    that never arrived) starts a keyframe and the grid restarts there, so no interval holds such a gap inside —
    a sample after it would be placed by the held rate's rotation (gaps eq. G1), off by tens of degrees over
    ½ s of motion; between keyframes the gap is one inflated preintegrated factor instead."""
    stride = max(1, int(stride))
    T = None if dt is None else float(np.median(dt))
    if T is not None and has_gap(np.asarray(dt)[:-1], T):
        ends = np.flatnonzero(np.asarray(dt)[:-1] > keyframe_gap_step(T)) + 1
        bounds = np.r_[0, ends, n]
        kf_samples = np.concatenate([np.arange(a, b, stride) for a, b in zip(bounds[:-1], bounds[1:])])
    else:
        kf_samples = np.arange(0, n, stride)
    if kf_samples[-1] != n - 1:
        kf_samples = np.append(kf_samples, n - 1)
    sample_kf = np.searchsorted(kf_samples, np.arange(n), side="right") - 1
    return kf_samples, sample_kf


@dataclass
class Preintegration:
    """Everything integrated from the gyro for one keyframe layout and bias estimate.

    Attributes:
        kf_samples: (K,) sample index of each keyframe.
        sample_kf: (N,) keyframe each sample is attached to.
        kRb: (N, 3, 3) rotation of each sample's body frame into its keyframe's body frame.
        delta_R: (K−1, 3, 3) ΔR between consecutive keyframes; dR_db (K−1, 3, 3); cov (K−1, 3, 3); dt (K−1,).
        bias_hat: (K−1, 3) bias used for each keyframe interval.
        steps: with keep_steps, per sample (N, 3, 3) kRb_j Exp(θ_j) J_r(θ_j) Δt_j, the summand of the bias and
            gyro-map Jacobians (calibration.gyro_map.map_jacobian); None otherwise.
        gap_end: (K−1,) bool, the interval's last step is a gap (samples that never arrived, gaps eq. G1: the
            layout puts every gap there); None: no gap.
    """

    kf_samples: np.ndarray
    sample_kf: np.ndarray
    kRb: np.ndarray
    delta_R: np.ndarray
    dR_db: np.ndarray
    cov: np.ndarray
    dt: np.ndarray
    bias_hat: np.ndarray
    steps: np.ndarray | None = None
    gap_end: np.ndarray | None = None


def preintegrate(b_gyr: np.ndarray, dt: np.ndarray, kf_samples: np.ndarray, sample_kf: np.ndarray,
                 bias_hat: np.ndarray, sigma_gyr: np.ndarray, rate_error: float = 0.0,
                 keep_steps: bool = False, gap_walk: float | None = GAP_RATE_WALK) -> Preintegration:
    """Integrate the gyro within every keyframe interval at once (loop over the position in the interval).

    Args:
        b_gyr: (N, 3) rad/s; dt: (N,) s, step from sample i to i+1; kf_samples, sample_kf: keyframe layout;
        bias_hat: (3,) or per-sample (N, 3) rad/s; sigma_gyr: (3,) discrete per-sample gyro noise std, rad/s;
        rate_error: κ, relative gyro error (scale factor and misalignment), dimensionless.
        keep_steps: also return each sample's kRb_j Exp(θ_j) J_r(θ_j)Δt_j (Preintegration.steps), formed in
            the recursion, where kRb_j Exp(θ_j) is the running product after step j (one batched product
            per position instead of two over all samples afterwards, and no copies of Exp(θ_j), J_r).
        gap_walk: q_ω of the steps with missing time (factors.gaps eq. G1; Preintegration.gap_end); None: off.
    """
    n = b_gyr.shape[0]
    k = len(kf_samples)
    bias_hat = np.asarray(bias_hat, float)
    bias_rows = np.broadcast_to(bias_hat, b_gyr.shape) if bias_hat.ndim == 1 else bias_hat[np.minimum(
        np.arange(b_gyr.shape[0]), len(bias_hat) - 1)]
    theta = (b_gyr - bias_rows) * dt[:, None]                 # (N,3) rotation increment of sample i
    rate2 = np.sum((b_gyr - bias_rows) ** 2, axis=1, keepdims=True)
    var_step = ((np.asarray(sigma_gyr, float) ** 2)[None, :] + rate_error**2 * rate2) * (dt**2)[:, None]
    T = float(np.median(dt)) if gap_walk is not None else 0.0
    gaps = gap_walk is not None and has_gap(dt, T)
    if gaps and np.any(sigma_gyr):                                # samples that never arrived: gaps eq. (G1)
        var_step = var_step + gap_variance(dt, T, gap_walk)[:, None]
    lengths = np.diff(np.append(kf_samples, n))               # samples attached to each keyframe
    L = int(lengths.max())
    # every keyframe interval laid out over L positions; positions past its end get the identity step
    # (Exp(0) = I, no bias-Jacobian or covariance increment), so the recursion runs on whole arrays
    pos = np.arange(L)
    valid = pos[:, None] < lengths[None, :]                   # (L, K): position p of keyframe k exists
    idx = np.where(valid, pos[:, None] + kf_samples[None, :], n)
    th_pad = np.concatenate([theta, np.zeros((1, 3))])[idx]  # θ = 0 past the end: Exp(0) = I, J_r = I
    dt_pad = np.append(dt, 0.0)[idx]                          # ... with Δt = 0: no bias-Jacobian step
    inc, jdt = exp_and_right_jacobian(th_pad)                 # (L, K, 3, 3) Exp(θ_j), J_r(θ_j)
    incT = np.transpose(inc, (0, 1, 3, 2))
    jdt *= dt_pad[:, :, None, None]
    var_pad = np.concatenate([var_step, np.zeros((1, 3))])[idx][:, :, :, None] * np.eye(3)
    R_at = np.empty((k, L, 3, 3))                             # ΔR_{k,j} before the step at position p
    cov_db = np.zeros((k, 3, 6))                              # [Σ_ΔR | ∂ΔR/∂b]: left products with Exp(θ)ᵀ
    left_R = np.zeros((k, 6, 3))                              # [Exp(θ)ᵀ Σ_ΔR ; ΔR]: right products with Exp(θ)
    left_R[:, 3:] = np.eye(3)
    P_at = np.empty((k, L, 3, 3)) if keep_steps else None    # kRb_j Exp(θ_j) J_r(θ_j) Δt_j
    for p in range(L):
        R_at[:, p] = left_R[:, 3:]
        cov_db = incT[p] @ cov_db
        left_R[:, :3] = cov_db[:, :, :3]
        left_R = left_R @ inc[p]
        if keep_steps:                                        # left_R[:, 3:] = ΔR_{k,j} Exp(θ_j) now
            np.matmul(left_R[:, 3:], jdt[p], out=P_at[:, p])
        cov_db[:, :, :3] = left_R[:, :3] + var_pad[p]
        cov_db[:, :, 3:] -= jdt[p]
    R = left_R[:, 3:]
    dRdb, cov = cov_db[:, :, 3:], cov_db[:, :, :3]
    regular = bool(np.all(lengths[:-1] == L))                 # regular layout: samples in (k, p) order
    if regular:
        kRb = R_at.reshape(-1, 3, 3)[:n]
    else:
        kRb = np.empty((n, 3, 3))
        kRb[idx.T[valid.T]] = R_at[valid.T]
    steps = None
    if keep_steps:                                            # (K, L) positions → samples, as kRb
        if regular:
            steps = P_at.reshape(-1, 3, 3)[:n]
        else:
            steps = np.empty((n, 3, 3))
            steps[idx.T[valid.T]] = P_at[valid.T]
    # Interval k integrated the increments of samples s_k .. s_{k+1}−1: exactly keyframe k → k+1.
    kf_dt = np.add.reduceat(dt, kf_samples)[:-1]
    gap_end = None
    if gaps:                                     # the step into each next keyframe
        gap_end = gap_steps(dt[kf_samples[1:] - 1], T)
    return Preintegration(kf_samples, sample_kf, kRb, R[:-1], dRdb[:-1], cov[:-1], kf_dt,
                          np.array(bias_rows[kf_samples[:-1]]), steps, gap_end)


def ahrs_factors(pre: Preintegration, key_rot, key_bias, sigma_gyr: np.ndarray) -> list:
    """One C++ `AHRSFactor` per keyframe interval, from the vectorised preintegration.

    key_bias: a key, or a function of the interval index giving the bias key (bias random walk).
    """
    bias_of = key_bias if callable(key_bias) else (lambda i: key_bias)
    params = gtsam.PreintegratedRotationParams()
    step = float(np.median(pre.dt) / max(1.0, float(np.median(np.diff(pre.kf_samples)))))
    params.setGyroscopeCovariance(np.diag(np.asarray(sigma_gyr, float) ** 2) * step)  # PSD σ_d²Δt
    out = []
    for i in range(len(pre.delta_R)):
        pim = gtsam.PreintegratedAhrsMeasurements(params, pre.bias_hat[i], float(pre.dt[i]),
                                                  gtsam.Rot3(pre.delta_R[i]), pre.dR_db[i], pre.cov[i])
        out.append(gtsam.AHRSFactor(key_rot(i), key_rot(i + 1), bias_of(i), pim))
    return out
