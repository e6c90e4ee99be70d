"""Orientation smoothing with a known calibration, from GTSAM's C++ factors only.

With θ fixed the magnetometer becomes a direction measurement: m_j = D⁻¹(y_j − o) (unit norm, inertial
axes; the magnetometer's lag `cal.mag_delay_s` removed first), covariance σ_m² D⁻¹D⁻ᵀ (GTSAM_NOTES:
MagFactor1 on the calibrated field). Every sample of a keyframe interval is rotated into the keyframe's
body frame with the preintegrated gyro ΔR_j and averaged, m̄_k = Σ_j ΔR_j m_j / n_k: one Huber-robust
magnetometer factor per keyframe (σ_m/(s√n_k)).

Linear acceleration, two treatments (`linear_acceleration`):

"velocity" (default) — linear acceleration as motion, the model of the batch path
(imugraph.factors.velocity): keyframe states (Pose3 X_k, nav-frame velocity V_k) joined by C++ `ImuFactor`s,

    v_{k+1} = v_k + n_grav Δt_k + R_k Δv_k + e_k,   Δv_k = Σ_j ΔR_kj a_j dt_j,   Σ_e = σ_dv,k² I

plus a first-order Gauss–Markov (bounded-velocity) prior, stationary std σ_v, correlation time τ_v:

    v_0 ~ N(0, σ_v² I),   v_{k+1} − φ_k v_k ~ N(0, σ_v²(1 − φ_k²) I),   φ_k = exp(−Δt_k/τ_v)

Each ImuFactor is built from ONE super-sample per interval, (ω, a, Δt) = (Log ΔR_k/Δt + b̂_ω, Δv_k/Δt, Δt),
which reproduces the vectorised preintegration's ΔR_k and Δv_k exactly (gtsam integrates the first sample
from the identity: ΔR = Exp(ωΔt), Δv = aΔt). Its noise model is replaced by block-diag(Σ_ΔR,k (gyro white
noise + rate error κ|ω|, as AHRSFactor), σ_p² I, σ_dv,k² I (accelerometer noise + κ_a|a|)). The position
part carries no information: the positions are free (one gauge prior on p_0), so they absorb every position
residual exactly; σ_p only sets their conditioning. The Gauss–Markov terms are linear in the velocity keys
and enter exactly as C++ `LinearContainerFactor`s around JacobianFactors (v_0 prior: `PriorFactorVector`).
The magnetometer factor is `MagPoseFactorPose3` (= MagFactor1 on the pose's rotation). The gyro bias is one
`imuBias.ConstantBias` per segment (bias_segment_s) joined by a random walk (`BetweenFactorConstantBias`),
as in the batch path; the accelerometer part of it is held at zero by a tight prior (the batch path has no
accelerometer bias either). g (magnitude of n_grav) closes the vertical velocity budget,
Σ_k (R_k Δv_k)_z = g T (velocity.gravity_from_velocity), evaluated at the initial orientations — first-order
insensitive to their tilt errors.

"noise" — the earlier treatment: linear acceleration as accelerometer noise, one Huber-robust
`AttitudeFactorRot3` per keyframe on the averaged accelerometer (nRef = up, σ_a/(g√n_k)), `MagFactor1` and
C++ `AHRSFactor`s on Rot3 keys. It fails on fast translation (BROAD 15: 22° RMS).

No Python callback exists in either graph, so gtsam's own Levenberg–Marquardt is used directly.
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from imugraph import keys
from imugraph.calibration.alignment import undelay_magnetometer
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.factors.gyro import Preintegration, ahrs_factors, keyframe_layout, preintegrate
from imugraph.factors.velocity import gauss_markov, gravity_from_velocity, velocity_increments
from imugraph.geometry import logmap
from imugraph.graphs.orientation_init import complementary_keyframes, sample_orientations
from imugraph.io.session import Session

MODES = ("velocity", "noise")


def _robust(model, k: float):
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), model)


def _imu_bias_key(i: int) -> int:
    """Key of the imuBias.ConstantBias (acc, gyro) of bias segment i ('b', distinct from keys.bias)."""
    return gtsam.symbol("b", int(i))


def smooth_fixed(session: Session, cal: Calibration, keyframe_hz: float = 10.0, huber_k: float = 2.0,
                 g: float | None = None, gyro_rate_error: float = 0.01, *,
                 linear_acceleration: str = "velocity", velocity_sigma: float = 0.5,
                 velocity_tau: float = 2.0, acc_rate_error: float = 0.01, acc_huber: bool = True,
                 bias_segment_s: float = 5.0, bias_rw: float = 2e-4, bias_prior_sigma: float = 0.01,
                 max_iterations: int = 100, acc_bias_sigma: float = 1e-4) -> np.ndarray:
    """Smoothed per-sample orientation (N, 4) w,x,y,z for a session with a known calibration.

    Args:
        session: the recording; cal: its calibration (D, o, dip, gyro bias, noise levels, magnetometer lag);
        keyframe_hz: keyframe rate; huber_k: Huber threshold (whitened units);
        g: gravity magnitude, m/s² (default: "velocity" closes the vertical velocity budget, "noise" takes
        the median |acc|); gyro_rate_error: κ, relative gyro error (scale factor, misalignment).
    Keyword-only ("velocity" treatment, see the module doc):
        linear_acceleration: "velocity" (linear acceleration as motion) or "noise" (as accelerometer noise);
        velocity_sigma: σ_v, stationary std of the sensor's velocity, m/s (hand-held / arm motion);
        velocity_tau: τ_v, its correlation time, s; acc_rate_error: κ_a, relative accelerometer error;
        acc_huber: Huber-robust velocity-increment factors (impacts, vibration);
        bias_segment_s: length of a gyro-bias segment, s (≤ 0: one bias); bias_rw: bias random-walk
        density, rad/s/√s; bias_prior_sigma: std of each segment's bias about cal.gyro_bias, rad/s;
        max_iterations: Levenberg–Marquardt iterations.

    Raises:
        SessionError: unknown `linear_acceleration`, or a session too short for two keyframes.
    """
    if linear_acceleration not in MODES:
        raise SessionError(session.name or "session", "linear_acceleration", repr(linear_acceleration),
                           " or ".join(MODES))
    stride = max(1, int(round(session.rate / keyframe_hz)))
    kf, skf = keyframe_layout(session.n, stride)
    if len(kf) < 2:
        raise SessionError(session.name or "session", "samples", str(session.n), f"at least {stride + 1}")
    sig_g = np.asarray(cal.noise.get("gyr", np.full(3, 0.005)), float)
    pre = preintegrate(session.gyr, session.dt, kf, skf, cal.gyro_bias, sig_g, gyro_rate_error)
    m_cal = cal.apply(undelay_magnetometer(session.t, session.mag, cal.mag_delay_s))
    valid = np.all(np.isfinite(m_cal), axis=1)
    K = len(kf)
    mag = np.zeros((K, 3)); np.add.at(mag, skf[valid], np.einsum("mij,mj->mi", pre.kRb[valid], m_cal[valid]))
    n_mag = np.bincount(skf[valid], minlength=K)
    tau = cal.coverage.get("noise_correlation", {}) if isinstance(cal.coverage, dict) else {}
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    sig_m = float(np.mean(cal.noise.get("mag", [0.01 * scale]))) * np.sqrt(tau.get("mag", 1.0)) / scale
    mag_avg = mag / np.maximum(n_mag, 1)[:, None]
    nRk0 = complementary_keyframes(pre, session.acc, m_cal)
    params = gtsam.LevenbergMarquardtParams()
    params.setOrderingType("METIS")
    params.setRelativeErrorTol(1e-7)
    params.setMaxIterations(int(max_iterations))
    if linear_acceleration == "noise":
        graph, values = _noise_graph(session, cal, pre, nRk0, mag_avg, n_mag, sig_m, sig_g, huber_k, g,
                                     tau.get("acc", 1.0))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        nRk = np.stack([result.atRot3(keys.rot(k)).matrix() for k in range(K)])
        return sample_orientations(nRk, pre)
    sig_acc = np.asarray(cal.noise.get("acc", np.full(3, 0.05)), float)
    dv, sig_dv = velocity_increments(pre.kRb, skf, session.acc, session.dt, K, sig_acc, acc_rate_error)
    if g is None:
        g = gravity_from_velocity(nRk0, np.zeros((K, 3)), dv, pre.dt)
    graph, values = _velocity_graph(session, cal, pre, nRk0, dv, sig_dv, float(g), mag_avg, n_mag, sig_m,
                                    (2.0 if acc_huber is True else acc_huber) if acc_huber else None, huber_k, velocity_sigma, velocity_tau,
                                    bias_segment_s, bias_rw, bias_prior_sigma, acc_bias_sigma)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    nRk = np.stack([result.atPose3(X(k)).rotation().matrix() for k in range(K)])
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
            mdl = models.setdefault(("a", n_acc[k]), _robust(gtsam.noiseModel.Isotropic.Sigma(2, sig_a / np.sqrt(n_acc[k])), huber_k))
            graph.add(gtsam.AttitudeFactorRot3(keys.rot(k), n_up, mdl, gtsam.Unit3(up[k])))
        if n_mag[k]:
            mdl = models.setdefault(("m", n_mag[k]), _robust(gtsam.noiseModel.Isotropic.Sigma(3, sig_m / np.sqrt(n_mag[k])), huber_k))
            graph.add(gtsam.MagFactor1(keys.rot(k), mag_avg[k], 1.0, n_field, np.zeros(3), mdl))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk0[k]))
    values.insert(keys.BIAS, np.asarray(cal.gyro_bias, float))
    return graph, values


# σ of the (information-free) position residuals and of the p_0 gauge prior, m; σ of the held-at-zero
# accelerometer bias, m/s²
_SIGMA_POS = 1.0
_SIGMA_ACC_BIAS = 1e-4


def _velocity_graph(session, cal, pre: Preintegration, nRk0, dv, sig_dv, g, mag_avg, n_mag, sig_m,
                    acc_huber, huber_k, sigma_v, tau_v, bias_segment_s, bias_rw, bias_prior_sigma,
                    acc_bias_sigma):
    """Pose3 + velocity keyframes joined by ImuFactors, Gauss–Markov velocity prior, MagPoseFactorPose3."""
    K = len(pre.kf_samples)
    bg = np.asarray(cal.gyro_bias, float)
    t_kf = session.t[pre.kf_samples[:-1]] - session.t[0]
    seg = (np.floor(t_kf / bias_segment_s).astype(int) if bias_segment_s > 0 else np.zeros(K - 1, int))
    n_seg = int(seg.max()) + 1
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    # ---- bias segments: prior about the calibration, random walk between segments
    zero3 = np.zeros(3)
    b_hat = gtsam.imuBias.ConstantBias(zero3, bg)
    prior_b = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, acc_bias_sigma), np.full(3, bias_prior_sigma)])
    seg_dt = float(pre.dt.sum()) / n_seg
    rw_b = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, _SIGMA_ACC_BIAS),
                                                  np.full(3, max(bias_rw, 1e-9) * np.sqrt(seg_dt))])
    for i in range(n_seg):
        values.insert(_imu_bias_key(i), b_hat)
        graph.add(gtsam.PriorFactorConstantBias(_imu_bias_key(i), b_hat, prior_b))
        if i:
            graph.add(gtsam.BetweenFactorConstantBias(_imu_bias_key(i - 1), _imu_bias_key(i),
                                                      gtsam.imuBias.ConstantBias(), rw_b))
    # ---- ImuFactors from one super-sample per interval, with the vectorised preintegration's noise
    p = gtsam.PreintegrationParams.MakeSharedU(g)
    omega = logmap(pre.delta_R) / pre.dt[:, None] + pre.bias_hat
    acc = dv / pre.dt[:, None]
    # rotation part (gyro; never robust) and velocity part (accelerometer; Huber) as two factors on the
    # same preintegration: zero rows of the square-root information drop the other part
    info_R = np.linalg.inv(pre.cov)
    sqrt_info = np.zeros((K - 1, 9, 9))
    sqrt_info[:, :3, :3] = np.transpose(np.linalg.cholesky(info_R), (0, 2, 1))
    prec_v = np.zeros((K - 1, 9))
    prec_v[:, 3:6] = 1.0 / _SIGMA_POS**2
    prec_v[:, 6:] = (1.0 / sig_dv**2)[:, None]
    for k in range(K - 1):
        pim = gtsam.PreintegratedImuMeasurements(p, gtsam.imuBias.ConstantBias(zero3, pre.bias_hat[k]))
        pim.integrateMeasurement(acc[k], omega[k], float(pre.dt[k]))
        f = gtsam.ImuFactor(X(k), keys.vel(k), X(k + 1), keys.vel(k + 1), _imu_bias_key(seg[k]), pim)
        graph.add(f.cloneWithNewNoiseModel(gtsam.noiseModel.Gaussian.SqrtInformation(sqrt_info[k])))
        model = gtsam.noiseModel.Diagonal.Precisions(prec_v[k])
        graph.add(f.cloneWithNewNoiseModel(_robust(model, acc_huber) if acc_huber else model))
    # ---- Gauss–Markov velocity prior (exactly linear in the velocity keys)
    phi, sig_w = gauss_markov(pre.dt, sigma_v, tau_v)
    graph.add(gtsam.PriorFactorVector(keys.vel(0), zero3, gtsam.noiseModel.Isotropic.Sigma(3, sigma_v)))
    unit3 = gtsam.noiseModel.Unit.Create(3)
    eye = np.eye(3)
    for k in range(K - 1):
        jf = gtsam.JacobianFactor(keys.vel(k), -phi[k] / sig_w[k] * eye, keys.vel(k + 1), eye / sig_w[k],
                                  zero3, unit3)
        lin = gtsam.Values()
        lin.insert(keys.vel(k), zero3)
        lin.insert(keys.vel(k + 1), zero3)
        graph.add(gtsam.LinearContainerFactor(jf, lin))
    # ---- magnetometer direction per keyframe; gauge of the (free) positions
    models: dict = {}
    for k in range(K):
        if n_mag[k]:
            mdl = models.setdefault(n_mag[k], _robust(gtsam.noiseModel.Isotropic.Sigma(3, sig_m / np.sqrt(n_mag[k])), huber_k))
            graph.add(gtsam.MagPoseFactorPose3(X(k), mag_avg[k], 1.0, cal.n_mag, zero3, mdl))
    graph.add(gtsam.PoseTranslationPrior3D(X(0), zero3, gtsam.noiseModel.Isotropic.Sigma(3, _SIGMA_POS)))
    v0, p0 = initial_motion(nRk0, dv, sig_dv, pre.dt, g, sigma_v, tau_v)
    for k in range(K):
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(nRk0[k]), p0[k]))
        values.insert(keys.vel(k), v0[k])
    return graph, values


def initial_motion(nRk: np.ndarray, dv: np.ndarray, sig_dv: np.ndarray, dt_k: np.ndarray, g: float,
                   sigma_v: float, tau_v: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocities (K, 3) minimising the velocity-increment and Gauss–Markov terms at fixed orientations
    nRk, and the positions (K, 3) that zero the (free) position residuals of the super-sample ImuFactors.

    The nav-frame axes decouple (isotropic σ), so this is one symmetric tridiagonal system per axis.
    """
    from scipy.linalg import solveh_banded

    K = len(nRk)
    n_grav = np.array([0.0, 0.0, -g])
    c = n_grav * dt_k[:, None] + np.einsum("kij,kj->ki", nRk[:-1], dv)      # v_{k+1} − v_k ≈ c_k
    a = 1.0 / sig_dv**2
    phi, sig_w = gauss_markov(dt_k, sigma_v, tau_v)
    b = 1.0 / sig_w**2
    diag = np.zeros(K); off = np.zeros(K - 1); rhs = np.zeros((K, 3))
    diag[0] += 1.0 / sigma_v**2
    diag[:-1] += a + b * phi**2
    diag[1:] += a + b
    off[:] = -a - b * phi
    rhs[:-1] -= a[:, None] * c
    rhs[1:] += a[:, None] * c
    ab = np.zeros((2, K)); ab[0, 1:] = off; ab[1] = diag
    v = solveh_banded(ab, rhs, lower=False)
    # gtsam's single-sample position increment: Δp = ½ aΔt² = ½ Δv Δt
    step = v[:-1] * dt_k[:, None] + 0.5 * c * dt_k[:, None]
    p = np.vstack([np.zeros(3), np.cumsum(step, axis=0)])
    return v, p
