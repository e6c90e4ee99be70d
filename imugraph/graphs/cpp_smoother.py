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

Options (off by default) for the batch / stream model's magnetometer (imugraph.graphs.cpp_field): the nav-field
perturbation d_k (`field_sigma`, `field_tau`), the stream's raw-field factor form (`mag_model="raw"`), per-keyframe
window offsets (`mag_offsets`); then the C++ solution is the start of a Python-driven Levenberg–Marquardt with the
magnetometer factors as one numpy block (BROAD, 17 trials, batch calibrations, 5 keyframes/s: with field_sigma
0.801° → 0.662° mean vs the optical truth, 0.38 → 0.66 s CPU mean, 0.91 s max; docs/stream.md "One model, two solvers").
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.dip_fold import folded_calibration
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
                 acc_lead_samples: float | None = None, field_sigma=None, field_tau: float = 1.0,
                 mag_model: str = "calibrated", mag_offsets: np.ndarray | None = None) -> np.ndarray:
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
        orientation moves more than this in an iteration (both stages with the field options).
      both: acc_lead_samples: δ, accelerometer row i paired with the orientation of row i + δ
        (calibration/acc_timing.py; None: the calibration's `acc_lead_samples`, as calibrate used it).
      "velocity" only, the batch / stream model's magnetometer (imugraph.graphs.cpp_field; any of them set:
      the C++ solve below is a warm start, then a Python-driven Levenberg–Marquardt, cpp_field.lm_solve):
        field_sigma: σ_d of the nav-field perturbation d_k per keyframe (scalar or per nav axis: along the
        horizontal field, across it, up; `calibration.ml.Options.field_sigma` = StreamOptions.field_sigma =
        (0.015, 0.003, 0.015)), field_tau: its τ_d, s; None (default): no perturbation (the field is n_mag);
        mag_model: "calibrated" (default: m̄_k = mean ΔR D⁻¹(y − o), full covariance) or "raw" (the stream's
        θ-state factor, stream_calstate eq. 1: ȳ_k = D M_k R_kᵀ(n + d_k) + o, covariance diag(σ_y²)/n_k);
        mag_offsets: (K, 3) raw-field offsets subtracted from keyframe k's field samples (a stream's windowed
        hard-iron offsets Δo_w); a NaN row: no magnetometer factor on that keyframe.

    A calibration with |dip| > 90° is folded first (calibration.dip_fold.folded_calibration: the same model, the nav
    frame turned by 180° about the vertical; the orientations are returned in that DESIGN-convention frame).

    Raises:
        SessionError: unknown `linear_acceleration` or `mag_model`, the field options with "noise", mag_offsets
        not (K, 3), or a session too short for two keyframes (fewer than 2 samples included).
    """
    from imugraph.graphs.cpp_field import MAG_MODELS

    name = session.name or "session"
    if session.n < 2:                  # no time step: no rate, no keyframe interval (U22 defect 10)
        raise SessionError(name, "samples", f"{session.n} sample{'s' if session.n != 1 else ''}",
                           "at least 2 samples (two keyframes)")
    cal = folded_calibration(cal)      # |dip| ≤ 90°: the initialisation assumes x along the horizontal field (U22 #1)
    if linear_acceleration not in MODES:
        raise SessionError(name, "linear_acceleration", repr(linear_acceleration), " or ".join(MODES))
    if mag_model not in MAG_MODELS:
        raise SessionError(name, "mag_model", repr(mag_model), " or ".join(MAG_MODELS))
    same_model = field_sigma is not None or mag_model != "calibrated" or mag_offsets is not None
    if same_model and linear_acceleration != "velocity":
        raise SessionError(name, "linear_acceleration", repr(linear_acceleration),
                           '"velocity" with field_sigma / mag_model / mag_offsets')
    if acc_lead_samples is None:
        acc_lead_samples = cal.acc_lead_samples
    velocity_sigma, velocity_tau = cal.velocity_process(velocity_sigma, velocity_tau)   # given, else the cal's
    if acc_lead_samples:
        from imugraph.calibration.acc_timing import with_lead
        session = with_lead(session, acc_lead_samples)
    stride = max(1, int(round(session.rate / keyframe_hz)))
    kf, skf = keyframe_layout(session.n, stride, session.dt)
    if len(kf) < 2:
        raise SessionError(name, "samples", str(session.n), f"at least {stride + 1}")
    sig_g = np.asarray(cal.noise.get("gyr", np.full(3, 0.005)), float)
    # ω = (I + E)·b_gyr − b: the calibration's gyro scale/misalignment E (zero when not estimated)
    pre = preintegrate(cal.corrected_gyro(session.gyr), session.dt, kf, skf, cal.gyro_bias, sig_g, gyro_rate_error)
    K = len(kf)
    y = cal.corrected(session.t, session.mag)
    if mag_offsets is not None:
        off = np.asarray(mag_offsets, float)
        if off.shape != (K, 3):
            raise SessionError(name, "mag_offsets", f"shape {off.shape}", f"({K}, 3): one row per keyframe")
        y = y - off[skf]
    m_cal = cal.apply(y)
    valid = np.all(np.isfinite(m_cal), axis=1)
    mag = np.zeros((K, 3)); np.add.at(mag, skf[valid], np.einsum("mij,mj->mi", pre.kRb[valid], m_cal[valid]))
    n_mag = np.bincount(skf[valid], minlength=K)
    mag_avg = mag / np.maximum(n_mag, 1)[:, None]
    tau = cal.coverage.get("noise_correlation", {}) if isinstance(cal.coverage, dict) else {}
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    nRk0 = complementary_keyframes(pre, session.acc, m_cal, borrow_field=False)   # no far keyframe's field in gaps
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
    warm = gtsam.NonlinearFactorGraph()
    warm.push_back(graph)
    for k in np.flatnonzero(n_mag):
        mdl = robust(gtsam.noiseModel.Gaussian.Covariance(cov_m[k]), huber_k)
        warm.add(gtsam.MagPoseFactorPose3(pose_key(k), mag_avg[k], 1.0, cal.n_mag, zero3, mdl))
    params.setOrdering(ordering)
    result = _iterate(warm, values, params, max_iterations, np.deg2rad(rotation_tol_deg))
    if same_model:       # the batch / stream model's magnetometer from the C++ solution (cpp_field)
        result = _same_model_solve(graph, result, ordering, pre, y, cal, sig_y, valid, huber_k, mag_model,
                                   field_sigma, field_tau, max_iterations, np.deg2rad(rotation_tol_deg))
    nRk = gtsam.utilities.extractPose3(result)[:, :9].reshape(-1, 3, 3)
    return sample_orientations(nRk, pre)


def _same_model_solve(graph, values, ordering, pre: Preintegration, y, cal, sig_y, valid, huber_k, mag_model,
                      field_sigma, field_tau, max_iterations, rotation_tol: float) -> gtsam.Values:
    """`graph` (the C++ velocity graph without magnetometer factors) + cpp_field's magnetometer block (eq. 2)
    and, with field_sigma, the d_k prior (eq. 1): Python-driven Levenberg–Marquardt from `values`, stopped as the
    C++ solve (`rotation_tol`, rad; cpp_field.lm_solve)."""
    from imugraph.factors.field import field_key
    from imugraph.graphs.cpp_field import FieldMagBlock, lm_solve, mag_terms, with_field_keys
    from imugraph.graphs.field_block import FieldBlock

    K = len(pre.kf_samples)
    field = field_sigma is not None
    block = FieldMagBlock(*mag_terms(mag_model, pre, y, cal, sig_y, valid, K), cal.n_mag, huber_k, field, K)
    full = gtsam.NonlinearFactorGraph()
    full.push_back(graph)
    x0 = gtsam.Values(values)
    if field:
        full.push_back(FieldBlock(pre.dt, field_sigma, field_tau).factors())
        for k in range(K):
            x0.insert(field_key(k), np.zeros(3))
    order = with_field_keys(ordering, keys.vel, K, field)
    return lm_solve(full, block, x0, order, max_iterations, rotation_tol)


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
