"""The single-IMU graph: keyframe orientations joined by preintegrated-gyro factors (C++ AHRSFactor),
every accelerometer and magnetometer sample attached to its keyframe (vectorised block), one gyro bias
and the shared magnetometer calibration θ = (vec D, o, δ).

    min  Σ_k ‖AHRS_k(R_k, R_{k+1}, b)‖²_Σω + Σ_j ρ(‖a_j − h_a(R_k, ΔR_j)‖_Σa)
           + Σ_j ρ(‖y_j − h_m(R_k, ΔR_j, θ)‖_Σm) + priors(b, θ)                 (Kok & Schön 2016, eq. 9)
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.gyro import Preintegration, ahrs_factors
from imugraph.factors.robust import QUADRATIC, Kernel
from imugraph.factors.theta import THETA_DIM
from imugraph.graphs.measurements import ChannelData, MeasurementBlock
from imugraph.graphs.solver import chain_ordering


@dataclass
class Noise:
    """Per-axis standard deviations: gyr rad/s (per sample), acc m/s², mag (magnetometer unit)."""

    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray

    def as_dict(self) -> dict:
        return {"gyr": np.asarray(self.gyr), "acc": np.asarray(self.acc), "mag": np.asarray(self.mag)}


@dataclass
class BlockAdapter:
    """Presents a MeasurementBlock to the solver in terms of gtsam.Values."""

    block: MeasurementBlock
    theta_fixed: np.ndarray | None = None

    def _state(self, values: gtsam.Values):
        nRk = np.stack([values.atRot3(keys.rot(k)).matrix() for k in range(self.block.n_keyframes)])
        theta = self.theta_fixed if self.theta_fixed is not None else values.atVector(keys.CALIB)
        return nRk, theta

    def cost(self, values: gtsam.Values) -> float:
        return self.block.cost(*self._state(values))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        return self.block.linear_factors(*self._state(values))


def channel(pre: Preintegration, values: np.ndarray, sigma, kernel: Kernel = QUADRATIC,
            weight_floor=None) -> ChannelData | None:
    """Attach the finite rows of a (N, 3) channel to their keyframes."""
    ok = np.all(np.isfinite(values), axis=1)
    if not ok.any():
        return None
    return ChannelData(kf=pre.sample_kf[ok], kRb=pre.kRb[ok], values=values[ok],
                       sigma=np.asarray(sigma, float), kernel=kernel,
                       weight_floor=None if weight_floor is None else weight_floor[ok])


@dataclass
class Problem:
    graph: gtsam.NonlinearFactorGraph
    blocks: list
    values: gtsam.Values
    ordering: gtsam.Ordering
    block: MeasurementBlock


def build_problem(pre: Preintegration, b_acc: np.ndarray, b_mag: np.ndarray, noise: Noise, g: float,
                  nRk0: np.ndarray, bias0: np.ndarray, theta0: np.ndarray | None,
                  theta_prior_sigma: np.ndarray | None = None, bias_prior_sigma: float = 0.05,
                  acc_kernel: Kernel = QUADRATIC, mag_kernel: Kernel = QUADRATIC,
                  estimate_theta: bool = True, mag_weights=None) -> Problem:
    """Assemble the graph for a keyframe layout.

    Args:
        pre: preintegration (layout, ΔR, gyro factors' data); b_acc (N,3) m/s²; b_mag (N,3) raw field
        (NaN rows = no sample); noise: per-axis stds; g: gravity magnitude; nRk0 (K,3,3) initial
        orientations; bias0 (3,); theta0 (13,) calibration (initial or fixed);
        estimate_theta: False keeps θ fixed at theta0 (smoothing with a known calibration).
    """
    K = len(pre.kf_samples)
    graph = gtsam.NonlinearFactorGraph()
    for f in ahrs_factors(pre, keys.rot, keys.BIAS, noise.gyr):
        graph.add(f)
    graph.add(gtsam.PriorFactorVector(keys.BIAS, np.asarray(bias0, float),
                                      gtsam.noiseModel.Isotropic.Sigma(3, bias_prior_sigma)))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.rot(k), gtsam.Rot3(nRk0[k]))
    values.insert(keys.BIAS, np.asarray(bias0, float))
    global_keys = [keys.BIAS]
    use_theta = estimate_theta and theta0 is not None
    if use_theta:
        values.insert(keys.CALIB, np.asarray(theta0, float))
        sig = theta_prior_sigma if theta_prior_sigma is not None else np.full(THETA_DIM, 10.0)
        graph.add(gtsam.PriorFactorVector(keys.CALIB, np.asarray(theta0, float),
                                          gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sig, float))))
        global_keys.append(keys.CALIB)
    block = MeasurementBlock(
        n_keyframes=K,
        acc=channel(pre, b_acc, noise.acc, acc_kernel),
        mag=channel(pre, b_mag, noise.mag, mag_kernel, mag_weights) if theta0 is not None else None,
        g=g, use_theta=use_theta)
    adapter = BlockAdapter(block, None if use_theta else (None if theta0 is None else np.asarray(theta0)))
    ordering = chain_ordering([keys.rot(k) for k in range(K)], global_keys)
    return Problem(graph, [adapter], values, ordering, block)


def keyframe_rotations(values: gtsam.Values, K: int) -> np.ndarray:
    return np.stack([values.atRot3(keys.rot(k)).matrix() for k in range(K)])
