"""Linear acceleration as motion from GTSAM's C++ factors only (the "velocity" graph of
`imugraph.graphs.cpp_smoother.smooth_fixed`): the model of the batch path (imugraph.factors.velocity),

    v_{k+1} = v_k + n_grav Δt_k + R_k Δv_k + e_k,   Δv_k = Σ_j ΔR_kj a_j dt_j,   e_k ~ N(0, σ_dv,k² I)
    v_0 ~ N(0, σ_v² I),   v_{k+1} − φ_k v_k ~ N(0, σ_v²(1 − φ_k²) I),   φ_k = exp(−Δt_k/τ_v)

expressed with built-in factors on keyframe states (Pose3 X_k, nav-frame velocity V_k):

* `ImuFactor` (or `ImuFactorWithGravityVector` when g is estimated) from ONE super-sample per interval,
  (ω, a, Δt) = (Log ΔR_k/Δt + b̂_ω, Δv_k/Δt, Δt). gtsam integrates a first sample from the identity
  (ΔR = Exp(ωΔt), Δv = aΔt), so the factor holds exactly the vectorised preintegration's ΔR_k and Δv_k
  (gyro rate error κ|ω| and accelerometer error κ_a|a| included), at one Python call per interval instead of
  one per sample. Its rows are [−Log(ΔR_kᵀ R_kᵀ R_{k+1}), position, −(R_k ΔR_k)ᵀ e_k]: the velocity row is
  the batch path's residual in the predicted body frame (same norm, and σ_dv is isotropic), exactly when
  the rotation row is zero and to first order in it otherwise (gtsam's NavState local coordinates).
  Two copies per interval with replaced noise models split it: the rotation rows (gyro, Σ_ΔR,k, never robust)
  and the velocity rows (accelerometer, σ_dv,k, Huber) — zero rows of the square-root information drop the
  other part, so a jolt of linear acceleration is down-weighted without loosening the gyro.
* The position rows carry no information: positions appear only in these factors and a gauge prior on p_0,
  so they absorb every position residual exactly (the super-sample's Δp = ½Δv Δt is never compared with
  anything); σ_p only sets their conditioning.
* The Gauss–Markov terms are linear in the velocity keys: `LinearContainerFactor`s around JacobianFactors
  [−φ_k I, I]/σ_w,k, exact for vector-valued keys, plus `PriorFactorVector` on v_0.
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from imugraph import keys
from imugraph.factors.gaps import bias_segments
from imugraph.factors.gyro import Preintegration
from imugraph.factors.velocity import gauss_markov
from imugraph.geometry import logmap

# σ of the (information-free) position rows and of the p_0 gauge prior, m; σ of the accelerometer-bias
# random walk between segments, m/s²; prior on the gravity vector: horizontal components held (a free
# horizontal g is a rotation of the whole solution about the field axis), magnitude loose, m/s²
SIGMA_POS = 1.0
SIGMA_ACC_BIAS_RW = 1e-4
SIGMA_G = np.array([1e-6, 1e-6, 0.5])
G_KEY = gtsam.symbol("g", 0)


def pose_key(k: int) -> int:
    """Key of keyframe k's Pose3 (rotation nRb = the orientation; translation: free positions)."""
    return X(int(k))


def imu_bias_key(i: int) -> int:
    """Key of the imuBias.ConstantBias (accelerometer, gyro) of bias segment i ('b', not keys.bias)."""
    return gtsam.symbol("b", int(i))


def robust(model, k: float | None):
    """Huber-robust version of a noise model (k in whitened units); None: the model itself."""
    if not k:
        return model
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(float(k)), model)


def super_samples(delta_R: np.ndarray, dv: np.ndarray, dt: np.ndarray, b_gyr: np.ndarray):
    """The (ω, a) of one gyro/accelerometer sample per interval that reproduces ΔR (M, 3, 3) and Δv (M, 3)
    over dt (M,) at gyro bias estimate b_gyr (M, 3): ω = Log ΔR / Δt + b̂, a = Δv / Δt."""
    dt = np.asarray(dt, float)[:, None]
    return logmap(np.asarray(delta_R, float)) / dt + b_gyr, np.asarray(dv, float) / dt


def super_sample_pim(params: gtsam.PreintegrationParams, omega: np.ndarray, acc: np.ndarray, dt: float,
                     b_gyr: np.ndarray) -> gtsam.PreintegratedImuMeasurements:
    """A preintegration of the single sample (acc, omega) over dt, at gyro bias estimate b_gyr."""
    pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias(np.zeros(3), b_gyr))
    pim.integrateMeasurement(acc, omega, float(dt))
    return pim


def split_noise(cov_R: np.ndarray, sigma_dv: np.ndarray, huber_k: float | None) -> list:
    """Per interval, (rotation-rows model, velocity-rows model) of the 9-row IMU residual
    [rotation, position, velocity]: cov_R (M, 3, 3) of ΔR, sigma_dv (M,) of Δv (m/s)."""
    sqrt_info = np.zeros((len(cov_R), 9, 9))
    sqrt_info[:, :3, :3] = np.transpose(np.linalg.cholesky(np.linalg.inv(cov_R)), (0, 2, 1))
    prec = np.zeros((len(cov_R), 9))
    prec[:, 3:6] = 1.0 / SIGMA_POS**2
    prec[:, 6:] = (1.0 / np.asarray(sigma_dv, float) ** 2)[:, None]
    return [(gtsam.noiseModel.Gaussian.SqrtInformation(sqrt_info[k]),
             robust(gtsam.noiseModel.Diagonal.Precisions(prec[k]), huber_k)) for k in range(len(cov_R))]


def gauss_markov_factors(dt_k: np.ndarray, sigma_v: float, tau_v: float, key=keys.vel) -> list:
    """The bounded-velocity prior as C++ factors: N(0, σ_v²) on v_0 and one exact linear factor per interval."""
    phi, sig_w = gauss_markov(dt_k, sigma_v, tau_v)
    zero3, eye, unit3 = np.zeros(3), np.eye(3), gtsam.noiseModel.Unit.Create(3)
    out = [gtsam.PriorFactorVector(key(0), zero3, gtsam.noiseModel.Isotropic.Sigma(3, sigma_v))]
    for k in range(len(dt_k)):
        jf = gtsam.JacobianFactor(key(k), -phi[k] / sig_w[k] * eye, key(k + 1), eye / sig_w[k], zero3, unit3)
        lin = gtsam.Values()
        lin.insert(key(k), zero3)
        lin.insert(key(k + 1), zero3)
        out.append(gtsam.LinearContainerFactor(jf, lin))
    return out


def velocity_graph(pre: Preintegration, t_kf: np.ndarray, nRk0: np.ndarray, dv: np.ndarray,
                   sig_dv: np.ndarray, g: float, estimate_g: bool, b_gyr: np.ndarray, o: dict):
    """Gyro, velocity-increment, bias and Gauss–Markov factors on Pose3 + velocity keyframes.

    Args:
        pre: preintegration at b_gyr; t_kf: (K−1,) start time of each interval from the session start, s;
        nRk0: (K, 3, 3) initial orientations; dv, sig_dv: velocity increments (K−1, 3) and their stds;
        g: gravity magnitude (start value when estimate_g); o: options (velocity_sigma, velocity_tau,
        acc_huber_k, acc_bias_sigma, bias_segment_s, bias_rw, bias_prior_sigma).
    Returns:
        graph, initial values, elimination ordering (keyframes in time, each bias segment after its
        keyframes, gravity last). The magnetometer factors are added by the caller.
    """
    K = len(pre.kf_samples)
    seg = bias_segments(t_kf, o["bias_segment_s"])      # renumbered past a declared gap longer than a segment
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    _bias_chain(graph, values, b_gyr, int(seg.max()) + 1, float(pre.dt.sum()), o)
    params = gtsam.PreintegrationParams.MakeSharedU(g)
    omega, acc = super_samples(pre.delta_R, dv, pre.dt, pre.bias_hat)
    models = split_noise(pre.cov, sig_dv, o["acc_huber_k"])
    for k in range(K - 1):
        pim = super_sample_pim(params, omega[k], acc[k], float(pre.dt[k]), pre.bias_hat[k])
        ends = (pose_key(k), keys.vel(k), pose_key(k + 1), keys.vel(k + 1), imu_bias_key(seg[k]))
        f = gtsam.ImuFactorWithGravityVector(*ends, G_KEY, pim) if estimate_g else gtsam.ImuFactor(*ends, pim)
        for model in models[k]:
            graph.add(f.cloneWithNewNoiseModel(model))
    for f in gauss_markov_factors(pre.dt, o["velocity_sigma"], o["velocity_tau"]):
        graph.add(f)
    zero3 = np.zeros(3)
    graph.add(gtsam.PoseTranslationPrior3D(pose_key(0), zero3, gtsam.noiseModel.Isotropic.Sigma(3, SIGMA_POS)))
    v0, p0 = initial_motion(nRk0, dv, sig_dv, pre.dt, g, o["velocity_sigma"], o["velocity_tau"])
    order = gtsam.Ordering()
    for k in range(K):
        values.insert(pose_key(k), gtsam.Pose3(gtsam.Rot3(nRk0[k]), p0[k]))
        values.insert(keys.vel(k), v0[k])
        order.push_back(pose_key(k))
        order.push_back(keys.vel(k))
        if k < K - 1 and (k == K - 2 or seg[k + 1] != seg[k]):
            order.push_back(imu_bias_key(seg[k]))
    if estimate_g:
        n_grav = np.array([0.0, 0.0, -g])
        values.insert(G_KEY, n_grav)
        graph.add(gtsam.PriorFactorVector(G_KEY, n_grav, gtsam.noiseModel.Diagonal.Sigmas(SIGMA_G)))
        order.push_back(G_KEY)
    return graph, values, order


def _bias_chain(graph, values, b_gyr: np.ndarray, n_seg: int, duration: float, o: dict) -> None:
    """One imuBias.ConstantBias per segment: prior about the calibration (gyro) and zero (accelerometer),
    random walk between segments (gyro σ = bias_rw·√(segment length))."""
    b_hat = gtsam.imuBias.ConstantBias(np.zeros(3), np.asarray(b_gyr, float))
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, o["acc_bias_sigma"]),
                                                   np.full(3, o["bias_prior_sigma"])])
    rw = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, SIGMA_ACC_BIAS_RW),
                                                np.full(3, max(o["bias_rw"], 1e-9) * np.sqrt(duration / n_seg))])
    for i in range(n_seg):
        values.insert(imu_bias_key(i), b_hat)
        graph.add(gtsam.PriorFactorConstantBias(imu_bias_key(i), b_hat, prior))
        if i:
            graph.add(gtsam.BetweenFactorConstantBias(imu_bias_key(i - 1), imu_bias_key(i),
                                                      gtsam.imuBias.ConstantBias(), rw))


def initial_motion(nRk: np.ndarray, dv: np.ndarray, sig_dv: np.ndarray, dt_k: np.ndarray, g: float,
                   sigma_v: float, tau_v: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocities (K, 3) minimising the increment and Gauss–Markov terms at fixed orientations nRk, and the
    positions (K, 3) that zero the position rows of the super-sample ImuFactors (initial values).

    The nav-frame axes decouple (σ isotropic): one symmetric tridiagonal system per axis.
    """
    from scipy.linalg import solveh_banded

    K = len(nRk)
    c = np.array([0.0, 0.0, -g]) * dt_k[:, None] + np.einsum("kij,kj->ki", nRk[:-1], dv)   # v_{k+1} − v_k
    a = 1.0 / sig_dv**2
    phi, sig_w = gauss_markov(dt_k, sigma_v, tau_v)
    b = 1.0 / sig_w**2
    diag = np.zeros(K)
    diag[0] += 1.0 / sigma_v**2
    diag[:-1] += a + b * phi**2
    diag[1:] += a + b
    rhs = np.zeros((K, 3))
    rhs[:-1] -= a[:, None] * c
    rhs[1:] += a[:, None] * c
    banded = np.zeros((2, K))
    banded[0, 1:] = -a - b * phi
    banded[1] = diag
    v = solveh_banded(banded, rhs, lower=False)
    step = v[:-1] * dt_k[:, None] + 0.5 * c * dt_k[:, None]      # gtsam's single-sample Δp = ½ Δv Δt
    return v, np.vstack([np.zeros(3), np.cumsum(step, axis=0)])
