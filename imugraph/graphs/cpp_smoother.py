"""Orientation smoothing with a known calibration, from GTSAM's C++ factors only.

With θ fixed the magnetometer becomes a direction measurement: m_j = D⁻¹(y_j − o) (unit norm, inertial
axes), covariance σ_m² D⁻¹D⁻ᵀ (GTSAM_NOTES: MagFactor1 on the calibrated field). Every sample of a
keyframe interval is rotated into the keyframe's body frame with the preintegrated gyro ΔR_j and averaged:

    ū_k = Σ_j ΔR_j a_j / n_k,   m̄_k = Σ_j ΔR_j m_j / n_k

giving one `AttitudeFactorRot3` (nRef = up, bMeasured = ū_k, σ_a/(g√n_k)) and one `MagFactor1`
(direction n_mag, σ_m/(s√n_k)) per keyframe, Huber-robust; keyframes are joined by C++ `AHRSFactor`s.
No Python callback exists in this graph, so gtsam's own Levenberg–Marquardt is used directly.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.alignment import undelay_magnetometer
from imugraph.calibration.result import Calibration
from imugraph.factors.gyro import ahrs_factors, keyframe_layout, preintegrate
from imugraph.graphs.orientation_init import complementary_keyframes, sample_orientations
from imugraph.io.session import Session


def _robust(model, k: float):
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), model)


def smooth_fixed(session: Session, cal: Calibration, keyframe_hz: float = 10.0, huber_k: float = 2.0,
                 g: float | None = None, gyro_rate_error: float = 0.01) -> np.ndarray:
    """Smoothed per-sample orientation (N, 4) w,x,y,z for a session with a known calibration.

    Args:
        session: the recording; cal: its calibration (D, o, dip, gyro bias, noise levels);
        keyframe_hz: keyframe rate; huber_k: Huber threshold (whitened units); g: gravity (default median |acc|).
    """
    stride = max(1, int(round(session.rate / keyframe_hz)))
    kf, skf = keyframe_layout(session.n, stride)
    sig_g = np.asarray(cal.noise.get("gyr", np.full(3, 0.005)), float)
    pre = preintegrate(session.gyr, session.dt, kf, skf, cal.gyro_bias, sig_g, gyro_rate_error)
    m_cal = cal.apply(undelay_magnetometer(session.t, session.mag, cal.mag_delay_s))
    valid = np.all(np.isfinite(m_cal), axis=1)
    K = len(kf)
    up = np.zeros((K, 3)); np.add.at(up, skf, np.einsum("mij,mj->mi", pre.kRb, session.acc))
    mag = np.zeros((K, 3)); np.add.at(mag, skf[valid], np.einsum("mij,mj->mi", pre.kRb[valid], m_cal[valid]))
    n_acc = np.bincount(skf, minlength=K)
    n_mag = np.bincount(skf[valid], minlength=K)
    g = g or float(np.median(np.linalg.norm(session.acc, axis=1)))
    tau = cal.coverage.get("noise_correlation", {}) if isinstance(cal.coverage, dict) else {}
    sig_a = float(np.mean(cal.noise.get("acc", [0.1]))) * np.sqrt(tau.get("acc", 1.0)) / g
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    sig_m = float(np.mean(cal.noise.get("mag", [0.01 * scale]))) * np.sqrt(tau.get("mag", 1.0)) / scale

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
            graph.add(gtsam.MagFactor1(keys.rot(k), mag[k] / n_mag[k], 1.0, n_field, np.zeros(3), mdl))
    values = gtsam.Values()
    nRk0 = complementary_keyframes(pre, session.acc, m_cal)
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk0[k]))
    values.insert(keys.BIAS, np.asarray(cal.gyro_bias, float))
    params = gtsam.LevenbergMarquardtParams()
    params.setOrderingType("METIS")
    params.setRelativeErrorTol(1e-7)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    nRk = np.stack([result.atRot3(keys.rot(k)).matrix() for k in range(K)])
    return sample_orientations(nRk, pre)
