"""Orientation smoothing with a known calibration, from GTSAM's C++ factors only.

With θ fixed the magnetometer becomes a direction measurement: m_j = D⁻¹(y_j − o) (unit norm, inertial
axes; `cal.corrected` first: the lag removed, disturbance-window offsets subtracted, unexplained windows
dropped). Every sample of a keyframe interval is rotated into the keyframe's body frame with the
preintegrated gyro ΔR_kj and averaged, m̄_k = Σ_j ΔR_kj m_j / n_k: one Huber-robust magnetometer factor per keyframe, with covariance

    Σ_m̄,k = Σ_j ΔR_kj D⁻¹ diag(σ_y²) D⁻ᵀ ΔR_kjᵀ / n_k²        (σ_y: per-axis noise of the raw field)

— the per-sample model of the batch path, averaged. (An isotropic σ_y/|D|^⅓ is far off when D is not close
to a sphere: with BROAD 15's calibration, D_zz = 4.4 against 45 µT on x, y, the z axis is 10× noisier than
that σ says, and the heading followed it: 2.8° → 1.35° RMS with the full covariance.)

Linear acceleration, two treatments (`linear_acceleration`):

"velocity" (default) — linear acceleration as motion, the batch path's model (imugraph.factors.velocity):
keyframe velocities driven by the accelerometer, with a bounded-velocity Gauss–Markov prior (σ_v, τ_v),
on Pose3 + velocity keyframes, from C++ ImuFactors and linear factors only (imugraph.graphs.cpp_velocity).
The magnetometer factor is `MagPoseFactorPose3` (MagFactor1 on the pose's rotation). The gyro bias is one
value per segment joined by a random walk, as in the batch path; the accelerometer bias is held at zero (as
in the batch path; freeing it, σ 0.1 m/s², made BROAD 15 and 21 worse: 1.3° → 2.9° and 2.5°). Gravity is a
variable (`ImuFactorWithGravityVector`; horizontal components held, magnitude started at the median |acc|):
its estimate closes the vertical velocity budget Σ_k (R_k Δv_k)_z ≈ g T, as velocity.gravity_from_velocity
does between the batch path's rounds, here jointly with the orientations.

"noise" — the earlier smoother, kept for comparison: linear acceleration as accelerometer noise, one
Huber-robust `AttitudeFactorRot3` per keyframe on the averaged accelerometer (nRef = up, σ_a/(g√n_k)),
`MagFactor1` with an isotropic σ, C++ `AHRSFactor`s on Rot3 keys. It fails on fast translation and near
magnets (BROAD 15: 22°, 30: 15° RMS).

No Python callback exists in either graph, so gtsam's own Levenberg–Marquardt is used directly.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.factors.gyro import Preintegration, ahrs_factors, keyframe_layout, preintegrate
from imugraph.factors.velocity import velocity_increments
from imugraph.graphs.cpp_velocity import pose_key, robust, velocity_graph
from imugraph.graphs.orientation_init import complementary_keyframes, sample_orientations
from imugraph.io.session import Session

MODES = ("velocity", "noise")


def smooth_fixed(session: Session, cal: Calibration, keyframe_hz: float = 5.0, huber_k: float = 2.0,
                 g: float | None = None, gyro_rate_error: float = 0.01, *,
                 linear_acceleration: str = "velocity", velocity_sigma: float | None = None,
                 velocity_tau: float | None = None,
                 acc_rate_error: float = 0.01, acc_huber_k: float | None = 2.0, acc_bias_sigma: float = 1e-4,
                 bias_segment_s: float = 5.0, bias_rw: float = 2e-4, bias_prior_sigma: float = 0.01,
                 max_iterations: int = 100, rotation_tol_deg: float = 0.05,
                 acc_lead_samples: float | None = None) -> np.ndarray:
    """Smoothed per-sample orientation (N, 4) w,x,y,z for a session with a known calibration.

    Args:
        session: the recording; cal: its calibration (D, o, dip, gyro bias and scale/misalignment E, noise
        levels, magnetometer lag);
        keyframe_hz: keyframe rate; huber_k: Huber threshold of the magnetometer (and, "noise", the
        accelerometer) factors, whitened units; gyro_rate_error: κ, relative gyro error.
        g: gravity magnitude, m/s², held fixed when given; None: "velocity" estimates it in the graph
        (started at the median |acc|), "noise" takes the median |acc|.
    Keyword-only:
        linear_acceleration: "velocity" (linear acceleration as motion, default) or "noise" (as
        accelerometer noise: the earlier smoother, kept for comparison).
      "velocity" only:
        velocity_sigma: σ_v, stationary std of the sensor's velocity, m/s; velocity_tau: τ_v, its
        correlation time, s (the batch path's start values; a hand-held or body-worn sensor);
        acc_rate_error: κ_a, relative accelerometer error (scale factor, misalignment);
        acc_huber_k: Huber threshold of the velocity increments (impacts, vibration), None: quadratic;
        acc_bias_sigma: std of the accelerometer bias, m/s² (default: held at zero, as the batch path);
        bias_segment_s: gyro-bias segment length, s (≤ 0: one bias); bias_rw: gyro-bias random-walk
        density, rad/s/√s; bias_prior_sigma: std of each segment's gyro bias about cal.gyro_bias, rad/s;
        max_iterations: Levenberg–Marquardt iterations at most; rotation_tol_deg: stop when no keyframe
        orientation moves more than this in an iteration.
      both: acc_lead_samples: δ, accelerometer row i paired with the orientation of row i + δ
        (calibration/acc_timing.py; None: the calibration's `acc_lead_samples`, as calibrate used it).

    Raises:
        SessionError: unknown `linear_acceleration`, or a session too short for two keyframes.
    """
    name = session.name or "session"
    if linear_acceleration not in MODES:
        raise SessionError(name, "linear_acceleration", repr(linear_acceleration), " or ".join(MODES))
    if acc_lead_samples is None:
        acc_lead_samples = cal.acc_lead_samples
    velocity_sigma, velocity_tau = cal.velocity_process(velocity_sigma, velocity_tau)   # given, else the cal's
    if acc_lead_samples:
        from imugraph.calibration.acc_timing import with_lead
        session = with_lead(session, acc_lead_samples)
    stride = max(1, int(round(session.rate / keyframe_hz)))
    kf, skf = keyframe_layout(session.n, stride)
    if len(kf) < 2:
        raise SessionError(name, "samples", str(session.n), f"at least {stride + 1}")
    sig_g = np.asarray(cal.noise.get("gyr", np.full(3, 0.005)), float)
    # ω = (I + E)·b_gyr − b: the calibration's gyro scale/misalignment E (zero when not estimated)
    pre = preintegrate(cal.corrected_gyro(session.gyr), session.dt, kf, skf, cal.gyro_bias, sig_g, gyro_rate_error)
    m_cal = cal.apply(cal.corrected(session.t, session.mag))
    valid = np.all(np.isfinite(m_cal), axis=1)
    K = len(kf)
    mag = np.zeros((K, 3)); np.add.at(mag, skf[valid], np.einsum("mij,mj->mi", pre.kRb[valid], m_cal[valid]))
    n_mag = np.bincount(skf[valid], minlength=K)
    mag_avg = mag / np.maximum(n_mag, 1)[:, None]
    tau = cal.coverage.get("noise_correlation", {}) if isinstance(cal.coverage, dict) else {}
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    nRk0 = complementary_keyframes(pre, session.acc, m_cal)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-7)
    params.setMaxIterations(int(max_iterations))
    if linear_acceleration == "noise":
        sig_m = float(np.mean(cal.noise.get("mag", [0.01 * scale]))) * np.sqrt(tau.get("mag", 1.0)) / scale
        graph, values = _noise_graph(session, cal, pre, nRk0, mag_avg, n_mag, sig_m, sig_g, huber_k, g,
                                     tau.get("acc", 1.0))
        params.setOrderingType("METIS")
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return sample_orientations(np.stack([result.atRot3(keys.rot(k)).matrix() for k in range(K)]), pre)
    # covariance of m̄_k: per sample diag(σ_y²) in raw units → D⁻¹ diag(σ_y²) D⁻ᵀ, rotated by ΔR_kj, / n_k²
    D_inv = np.linalg.inv(cal.D)
    sig_y = np.asarray(cal.noise.get("mag", np.full(3, 0.01 * scale)), float) * np.sqrt(tau.get("mag", 1.0))
    S_m = D_inv @ np.diag(sig_y**2) @ D_inv.T
    cov_m = np.zeros((K, 3, 3))
    np.add.at(cov_m, skf[valid], pre.kRb[valid] @ S_m @ np.transpose(pre.kRb[valid], (0, 2, 1)))
    cov_m /= np.maximum(n_mag, 1)[:, None, None] ** 2
    sig_acc = np.asarray(cal.noise.get("acc", np.full(3, 0.05)), float)
    dv, sig_dv = velocity_increments(pre.kRb, skf, session.acc, session.dt, K, sig_acc, acc_rate_error)
    opts = dict(velocity_sigma=velocity_sigma, velocity_tau=velocity_tau, acc_huber_k=acc_huber_k,
                acc_bias_sigma=acc_bias_sigma, bias_segment_s=bias_segment_s, bias_rw=bias_rw,
                bias_prior_sigma=bias_prior_sigma)
    g0 = float(g) if g is not None else float(np.median(np.linalg.norm(session.acc, axis=1)))
    t_kf = session.t[kf[:-1]] - session.t[0]
    graph, values, ordering = velocity_graph(pre, t_kf, nRk0, dv, sig_dv, g0, g is None,
                                             np.asarray(cal.gyro_bias, float), opts)
    zero3 = np.zeros(3)
    for k in np.flatnonzero(n_mag):
        mdl = robust(gtsam.noiseModel.Gaussian.Covariance(cov_m[k]), huber_k)
        graph.add(gtsam.MagPoseFactorPose3(pose_key(k), mag_avg[k], 1.0, cal.n_mag, zero3, mdl))
    params.setOrdering(ordering)
    result = _iterate(graph, values, params, max_iterations, np.deg2rad(rotation_tol_deg))
    nRk = gtsam.utilities.extractPose3(result)[:, :9].reshape(-1, 3, 3)
    return sample_orientations(nRk, pre)


def _noise_graph(session, cal, pre: Preintegration, nRk0, mag_avg, n_mag, sig_m, sig_g, huber_k, g, tau_acc):
    """Rot3 keyframes, AHRSFactor, per-keyframe AttitudeFactorRot3 and MagFactor1 (linear acc. as noise)."""
    K = len(pre.kf_samples)
    up = np.zeros((K, 3)); np.add.at(up, pre.sample_kf, np.einsum("mij,mj->mi", pre.kRb, session.acc))
    n_acc = np.bincount(pre.sample_kf, minlength=K)
    g = g or float(np.median(np.linalg.norm(session.acc, axis=1)))
    sig_a = float(np.mean(cal.noise.get("acc", [0.1]))) * np.sqrt(tau_acc) / g
    graph = gtsam.NonlinearFactorGraph()
    for f in ahrs_factors(pre, keys.rot, keys.BIAS, sig_g):
        graph.add(f)
    graph.add(gtsam.PriorFactorVector(keys.BIAS, np.asarray(cal.gyro_bias, float),
                                      gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
    n_up, n_field = gtsam.Unit3(np.array([0.0, 0.0, 1.0])), gtsam.Unit3(cal.n_mag)
    models: dict = {}
    for k in range(K):
        if n_acc[k]:
            mdl = models.setdefault(("a", n_acc[k]), robust(gtsam.noiseModel.Isotropic.Sigma(2, sig_a / np.sqrt(n_acc[k])), huber_k))
            graph.add(gtsam.AttitudeFactorRot3(keys.rot(k), n_up, mdl, gtsam.Unit3(up[k])))
        if n_mag[k]:
            mdl = models.setdefault(("m", n_mag[k]), robust(gtsam.noiseModel.Isotropic.Sigma(3, sig_m / np.sqrt(n_mag[k])), huber_k))
            graph.add(gtsam.MagFactor1(keys.rot(k), mag_avg[k], 1.0, n_field, np.zeros(3), mdl))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk0[k]))
    values.insert(keys.BIAS, np.asarray(cal.gyro_bias, float))
    return graph, values


def _iterate(graph, values, params, max_iterations: int, rotation_tol: float) -> gtsam.Values:
    """gtsam's Levenberg–Marquardt, one iteration at a time, stopped when no keyframe orientation moves by
    more than `rotation_tol` (rad) in an iteration (or by gtsam's own error tolerances).

    The robust (Huber) velocity factors give the cost a long, slowly converging tail (velocities and
    positions settling) in which the orientations no longer change.
    """
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    prev = gtsam.utilities.extractPose3(values)[:, :9].reshape(-1, 3, 3)
    err = graph.error(values)
    for _ in range(int(max_iterations)):
        opt.iterate()
        new_err = opt.error()
        cur = gtsam.utilities.extractPose3(opt.values())[:, :9].reshape(-1, 3, 3)
        # rotation angle of prevᵀ·cur from its trace
        tr = np.einsum("kij,kij->k", prev, cur)
        moved = float(np.arccos(np.clip((tr.min() - 1.0) / 2.0, -1.0, 1.0)))
        prev = cur
        if moved < rotation_tol or not new_err < err or (err - new_err) < params.getRelativeErrorTol() * err:
            break
        err = new_err
    return opt.values()
