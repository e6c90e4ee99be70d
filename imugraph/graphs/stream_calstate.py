"""The magnetometer calibration as a state of the stream's graph: θ = (vec D, o, δ) estimated jointly with the
keyframe orientations, as the batch model does (imugraph.factors.magnetometer, calibration.ml).

Why: the closed-form refit (stream_calib) treats the orientations as known, but they were estimated with the
start calibration, so it inherits that calibration's error (errors in variables: BROAD 06, 7.9 combined std
from the whole-trial batch; from the batch's calibration instead, 3.0). Here one 13-vector key θ (`keys.CALIB`,
packed as `factors.theta`) is in every keyframe's magnetometer factor; the incremental solver estimates it with
the orientations, and when keyframes leave the fixed-lag window their information about θ stays in the
marginal factor on (θ, the window) — the Schur complement of the marginalised keyframes, conditioned jointly.

Keyframe k's magnetometer factor on (pose_k, d_k, θ), on the interval's raw field averaged (valid samples i,
ΔR_i = kRb_i the gyro rotation of sample i into keyframe k, Kok & Schön's model y_i = D ΔR_iᵀ R_kᵀ n + o + e_i
with the field perturbation d_k of stream_field eq. (1)):

    ȳ_k = mean_i y_i = D M_k R_kᵀ (n(δ) + d_k) + o + ē_k,   M_k = mean_i ΔR_iᵀ,   cov ē_k = diag(σ_y²) / n_k   (1)

    e = D w + o − ȳ_k,  u = R_kᵀ(n + d_k),  w = M_k u:
    ∂e/∂ω = D M_k [u]×,  ∂e/∂d_k = D M_k R_kᵀ,  ∂e/∂vec D = I₃ ⊗ wᵀ,  ∂e/∂o = I₃,  ∂e/∂δ = D M_k R_kᵀ n'(δ)   (2)

(right perturbation R_k Exp(ω); gtsam's Pose3 tangent [ω, v], zero in the position; n'(δ) = (−sin δ, 0, −cos δ)).
Like stream_field's factor it is linearised once, at keyframe k's estimate and the current θ̂ when its interval
closes, and held as a C++ `LinearContainerFactor` (whitened, Huber weight frozen there): no Python call in the
solver. Neglected: second order in the later corrections, |D M [u]× ω| for a D change ΔD: ≈ |ΔD|·|ω| (1 % of the
scale × 1° = 1.7e-4 of the field, against σ_y/√n ≈ 2e-3).

θ is PINNED at the start calibration θ₀ (a prior with σ = `PIN_REL` of the weak prior's σ): the orientations and
the filtered output are those of the start calibration held fixed (measured on BROAD 06, 10, 12 with θ free
instead, same bootstraps: filtered 1.44 → 1.94°, 0.59 → 1.46°, 0.59 → 1.38° — a calibration that moves during the trial moves
the heading with it), while the solver still carries what the data say about θ jointly with the orientations:
eliminating every other variable before θ (θ is a global key, at the root; keyframes leaving the lag window
keep their part in the marginal factor on θ and the window) leaves on θ the pin's information Λ_p plus the data's
Schur complement S = H_θθ − H_θx H_xx⁻¹ H_xθ, and a gradient g (the orientations x profiled out). From iSAM2's
marginal covariance P of θ and its estimate θ̂:

    P⁻¹ = Λ_p + S,   P⁻¹ (θ̂ − θ₀) = g                                                                   (3)
    streamed θ = θ₀ + (S + Λ_w)⁻¹ P⁻¹ (θ̂ − θ₀),   its covariance (S + Λ_w)⁻¹                               (4)

with Λ_w the weak prior about θ₀ (D, o ± calib_prior_rel × field scale, δ ± 90°, as calibration.ml's): one
Gauss–Newton step of the joint problem (orientations and θ) from θ₀, the errors-in-variables correction the
closed-form refit on fixed orientations misses (its information is H_θθ, not S). The start's own std is not used
as the prior: a bootstrap was computed from the same samples. Std: `std_white` is the square root of (4)'s
diagonal under the stream's noise model (σ_y of the calibration × √(its noise-correlation factor), Huber
weights frozen), as the batch reports its own; the reported `std` is that × √max(1, V_j) (eq. 6). With the pin
at 1e-4 of the weak σ the data move θ̂ by ≈ (S/Λ_p) of the correction (measured at the end of BROAD 06 / 01:
0.05 / 0.1 % in D, o; 0.007° / 0.003° in the dip, 0.5 / 0.8 %), so the orientations are those of θ₀.

Linearisation point of θ in new magnetometer factors: θ₀ until the streamed θ is well determined (every std
of D, o < `StreamOptions.calib_lin_rel` × field scale, 1 %), then the latest streamed θ_s. The model is linear in
θ for a given orientation, so at the pinned θ₀ such a factor's residual is still exactly that of θ₀ (the
orientations are unaffected); what changes is the orientation Jacobian D_s M [u]× and so the neglected cross
term of the joint Gauss–Newton step, (D − D_lin) M [u]× ω, from the whole correction to what is left of it.
Measured on BROAD 06 (bootstrap 5 % of the field scale off the whole-trial batch): last streamed θ vs batch
max z 5.3 linearised at θ₀ → 2.7 at θ_s, filtered 1.43 → 1.25°.                                              (5)
"""

from __future__ import annotations

import math
from dataclasses import replace

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.result import Calibration
from imugraph.factors.theta import THETA_DIM, pack_theta, unpack_theta
from imugraph.geometry import skew

__all__ = ["CAL_KEY", "PIN_REL", "WhitenessSums", "cal_mag_factor", "cal_mag_jacobians", "calibration_of", "data_estimate",
           "pinned_mag_factor", "weak_sigmas", "theta_of"]

CAL_KEY = keys.CALIB
PIN_REL = 1e-4        # σ of the pin on θ, relative to the weak prior's σ (eq. 3)
_UNIT3 = gtsam.noiseModel.Unit.Create(3)


def theta_of(cal: Calibration) -> np.ndarray:
    """θ (13,) of a calibration: vec D (row-major), o, δ in rad (factors.theta)."""
    return pack_theta(cal.D, cal.o, np.deg2rad(cal.dip_deg))


def calibration_of(cal: Calibration, theta: np.ndarray, cov: np.ndarray | None) -> Calibration:
    """`cal` with D, o, dip from θ and std from the diagonal of its covariance (13×13; None: no std)."""
    D, o, dip = unpack_theta(theta)
    std = None
    if cov is not None:
        s = np.sqrt(np.maximum(np.diag(cov), 0.0))
        std = {"D": s[:9].reshape(3, 3), "o": s[9:12].copy(), "dip_deg": float(np.rad2deg(s[12]))}
    return replace(cal, D=D, o=o, dip_deg=float(np.rad2deg(dip)), std=std)


def weak_sigmas(cal: Calibration, rel: float) -> np.ndarray:
    """σ (13,) of the weak prior Λ_w about θ₀: D, o ± rel × field scale, δ ± 90° (as calibration.ml's weak prior)."""
    scale = float(np.cbrt(abs(np.linalg.det(cal.D)))) or 1.0
    return np.r_[np.full(12, rel * scale), np.pi / 2]


def data_estimate(theta_hat: np.ndarray, P: np.ndarray, theta0: np.ndarray, pin_sig: np.ndarray,
                  weak_sig: np.ndarray, prior_mean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (3)–(4): the streamed θ and its covariance from the pinned solver's θ̂ and marginal covariance P.
    prior_mean: the centre c of the weak prior Λ_w (None: θ₀); then (4) reads
    θ = θ₀ + (S + Λ_w)⁻¹ (P⁻¹(θ̂ − θ₀) + Λ_w (c − θ₀))  (the minimum of the data's quadratic about θ₀ plus the prior)."""
    info = np.linalg.inv(P)
    info = 0.5 * (info + info.T)
    lam_w = 1.0 / np.asarray(weak_sig, float) ** 2
    S = info - np.diag(1.0 / np.asarray(pin_sig, float) ** 2)          # the data's Schur complement
    A = S + np.diag(lam_w)
    cov = np.linalg.inv(A)
    g = info @ (np.asarray(theta_hat, float) - theta0)
    if prior_mean is not None:
        g = g + lam_w * (np.asarray(prior_mean, float) - theta0)
    return theta0 + cov @ g, 0.5 * (cov + cov.T)


def cal_mag_jacobians(R_k: np.ndarray, d: np.ndarray, theta: np.ndarray, M: np.ndarray, y_avg: np.ndarray):
    """Eq. (2): error e (3,) and Jacobians w.r.t. the pose (3×6), d_k (3×3) and θ (3×13) at (R_k, d, θ): the
    batch model's rows (`factors.magnetometer.magnetometer_rows`) of one "sample" whose ΔRᵀ is the interval's
    mean M (the model is linear in ΔRᵀ): e = D M R_kᵀ(n + d) + o − ȳ, ∂e/∂ξ = D M [R_kᵀ(n + d)]×, ∂e/∂d = D M R_kᵀ,
    ∂e/∂vec D = I₃ ⊗ (M v)ᵀ, ∂e/∂o = I₃, ∂e/∂δ = D M R_kᵀ n'(δ). Written out for one row block (the general
    function's (M, 3, 17) layout cost ≈ 0.2 ms per keyframe; equal to it to 1e-12, tests/test_stream_calstate.py).
    The 3×3 products stay numpy's: in Python floats (no fused multiply-add) they were 2× faster but moved BROAD 15's
    end D by 2e-9 (its weakly determined θ amplifies rounding)."""
    th = np.asarray(theta, float)
    D, o, dip = th[:9].reshape(3, 3), th[9:12], float(th[12])
    cd, sd = math.cos(dip), math.sin(dip)
    Rt = np.asarray(R_k, float).T
    v = Rt @ (np.array([cd, 0.0, -sd]) + np.asarray(d, float))  # v = R_kᵀ (n + d_k)
    DM = D @ np.asarray(M, float)                                # D M
    u = M @ v                                                    # M v
    (u0, u1, u2), (vx, vy, vz) = u.tolist(), v.tolist()
    c0, c1, c2 = (DM @ (Rt @ np.array([-sd, 0.0, -cd]))).tolist()   # D M R_kᵀ n'(δ)
    J_th = np.array([[u0, u1, u2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, c0],       # I₃ ⊗ uᵀ, I₃, ∂/∂δ
                     [0.0, 0.0, 0.0, u0, u1, u2, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, c1],
                     [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, u0, u1, u2, 0.0, 0.0, 1.0, c2]])
    J_pose = np.zeros((3, 6))
    J_pose[:, :3] = DM @ np.array([[0.0, -vz, vy], [vz, 0.0, -vx], [-vy, vx, 0.0]])   # D M [v]×
    e = D @ u + o - np.asarray(y_avg, float)
    # the products are numpy's (BLAS) as before, only the arrays are built with fewer calls: the same bits
    return e, J_pose, DM @ Rt, J_th


def cal_mag_factor(pose_k: int, pose: gtsam.Pose3, field_k: int | None, d: np.ndarray, theta: np.ndarray,
                   kRb: np.ndarray, y: np.ndarray, sig_y: np.ndarray, huber_k: float | None,
                   theta_pin: np.ndarray | None = None, gate: float | None = None, offset_key: int | None = None,
                   offset: np.ndarray | None = None, info: dict | None = None):
    """Keyframe k's magnetometer factor (1) on (pose_k, d_k — None: no field perturbation —, θ), linearised at
    (pose, d, θ) and held as a LinearContainerFactor. kRb (n, 3, 3) and y (n, 3): the interval's samples (rows
    with a NaN field are not used); sig_y (3,): σ of one sample.

    gate (field units): a keyframe whose mean residual |e| at (pose, θ_pin) exceeds it (a disturbance) gives no
    information on θ: its factor is on (pose_k, d_k) only, with the residual at θ_pin (the graph's pinned θ),
    i.e. what the θ factor gives the orientations there. Returns (factor, rows): rows = (G, a), the whitened
    (no Huber weight) residual as a function of θ at this pose, r(θ) = G θ + a (eq. 6), or None when gated;
    (None, None) when no sample is valid.

    offset_key: a disturbance window's hard-iron offset Δo_w (stream_offsets eq. 1: ȳ_k = D M_k R_kᵀ(n + d_k) + o + Δo_w,
    ∂e/∂Δo_w = I), linearised at `offset` (None: at the value that zeroes the residual at (pose, θ_pin): a new
    window's start). info (a dict, filled when given): n (valid samples), r2 (|whitened residual at (pose, θ_pin,
    offset)|²), offset (the Δo_w used)."""
    if math.isfinite(float(y.sum())):                        # every row has a field (a sum is finite iff all its
        n = len(y)                                           # terms are): no mask, no fancy indexing
        if n == 0:
            return None, None
        sum_R, sum_y = kRb.sum(axis=0), y.sum(axis=0)
    else:
        ok = np.all(np.isfinite(y), axis=1)
        n = int(ok.sum())
        if n == 0:
            return None, None
        sum_R, sum_y = kRb[ok].sum(axis=0), y[ok].sum(axis=0)
    M = sum_R.T / n                                          # mean ΔR_iᵀ (as ndarray.mean: the sum, then / n)
    d3 = np.zeros(3) if field_k is None else np.asarray(d, float)
    theta = np.asarray(theta, float)
    e, J_pose, J_d, J_th = cal_mag_jacobians(pose.rotation().matrix(), d3, theta, M, sum_y / n)
    inv_sig = np.sqrt(n) / np.asarray(sig_y, float)          # whitening by cov ē = diag(σ_y²)/n
    # the residual at the pinned θ, which the orientations were estimated with (exact: (1) is linear in θ at a pose)
    e_pin = e if theta_pin is None else e + J_th @ (np.asarray(theta_pin, float) - theta)
    if offset_key is not None:                               # + Δo_w (stream_offsets eq. 1), linear in it
        offset = -e_pin if offset is None else np.asarray(offset, float)
        e, e_pin = e + offset, e_pin + offset
    if info is not None:
        info.update(n=n, r2=float(np.sum((inv_sig * e_pin) ** 2)), offset=offset)
    gated = gate is not None and math.sqrt(float(e_pin @ e_pin)) > gate        # |e_pin| (as np.linalg.norm)
    if gated:
        e = e_pin
    r = inv_sig * e
    # Huber (gtsam's Robust.WhitenSystem): weight 1 within k whitened units, k/|r| beyond; √weight on A and b
    r_norm = math.sqrt(float(r @ r))
    sw = 1.0 if not huber_k or r_norm <= huber_k else math.sqrt(huber_k / r_norm)
    W = (sw * inv_sig)[:, None]
    lin = gtsam.Values()
    lin.insert(pose_k, pose)
    blocks = [pose_k, W * J_pose]
    # gtsam's Python JacobianFactor takes at most three keys: with θ and Δo_w, d_k is held at its estimate here
    # (the window keyframe's field perturbation is then not observed by this factor; stream_offsets)
    if field_k is not None and (offset_key is None or gated):
        lin.insert(field_k, d3)
        blocks += [field_k, W * J_d]
    if not gated:
        lin.insert(CAL_KEY, theta)
        blocks += [CAL_KEY, W * J_th]
    if offset_key is not None:
        lin.insert(offset_key, offset)
        blocks += [offset_key, np.diagflat(W)]
    jf = gtsam.JacobianFactor(*blocks, -sw * r, _UNIT3)
    rows = None if gated else (inv_sig[:, None] * J_th, inv_sig * (e - J_th @ theta))
    return gtsam.LinearContainerFactor(jf, lin), rows


def pinned_mag_factor(pose_k: int, field_k: int | None, offset_key: int | None, theta0: np.ndarray, kRb: np.ndarray,
                      y: np.ndarray, sig_y: np.ndarray, huber_k: float | None):
    """Eq. (1) at the pinned θ₀, exact (a CustomFactor on pose_k, d_k — None: none — and a window's Δo_w): the
    end-of-stream graph's magnetometer factor, e = D M_k R_kᵀ(n + d_k) + o (+ Δo_w) − ȳ_k, Σ = diag(σ_y²)/n_k, Huber;
    Jacobians eq. (2) without the θ block. None without a valid sample."""
    ok = np.all(np.isfinite(y), axis=1)
    n = int(ok.sum())
    if n == 0:
        return None
    D, o, dip = unpack_theta(theta0)
    n_vec = np.array([math.cos(dip), 0.0, -math.sin(dip)])
    DM, b = D @ (kRb[ok].sum(axis=0).T / n), y[ok].sum(axis=0) / n - o
    keys_ = [pose_k] + ([field_k] if field_k is not None else []) + ([offset_key] if offset_key is not None else [])

    def error(this, values, H):
        Rt = values.atPose3(pose_k).rotation().matrix().T
        v = Rt @ (n_vec + (values.atVector(field_k) if field_k is not None else 0.0))
        e = DM @ v - b + (values.atVector(offset_key) if offset_key is not None else 0.0)
        if H is not None:
            Jp = np.zeros((3, 6))
            Jp[:, :3] = DM @ skew(v)
            H[0] = Jp
            i = 1
            if field_k is not None:
                H[i], i = DM @ Rt, i + 1
            if offset_key is not None:
                H[i] = np.eye(3)
        return e

    model = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sig_y, float) / math.sqrt(n))
    if huber_k:
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(float(huber_k)), model)
    return gtsam.CustomFactor(model, keys_, error)


class WhitenessSums:
    """Eq. (6): the batch-means long-run variance of the whitened θ residuals, per magnetometer axis j,

        V_j(θ) = Σ_b (Σ_{k∈b} r_kj(θ))² / N,   r_k(θ) = G_k θ + a_k (each keyframe at its linearisation pose)   (6)

    over blocks b (the stream's calib_every_s), N keyframes: 1 for white residuals at the nominal noise, larger when
    they are larger or correlated over the block (the field varying with position, disturbances, orientation
    errors that persist). The streamed std of row j of D and of o_j is scaled by √max(1, V_j) (the dip's by the
    largest), as stream_calib's refit scales its own (its eq. 3). Constant memory: per axis one 14×14 matrix."""

    def __init__(self):
        self.Q = np.zeros((3, THETA_DIM + 1, THETA_DIM + 1))
        self.n = 0
        self._g, self._a, self._nb = np.zeros((3, THETA_DIM)), np.zeros(3), 0

    def add(self, G: np.ndarray, a: np.ndarray) -> None:
        self._g += G
        self._a += a
        self._nb += 1

    def end_block(self) -> None:
        if self._nb:
            v = np.hstack([self._g, self._a[:, None]])             # (3, 14): row j = (Σ G_j, Σ a_j)
            self.Q += v[:, :, None] * v[:, None, :]
            self.n += self._nb
        self._g[:], self._a[:], self._nb = 0.0, 0.0, 0

    def factor(self, theta: np.ndarray) -> np.ndarray | None:
        """V_j(θ) (3,), or None before any block."""
        if not self.n:
            return None
        x = np.r_[np.asarray(theta, float), 1.0]
        return np.einsum("i,jik,k->j", x, self.Q, x) / self.n
