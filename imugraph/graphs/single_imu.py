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
from imugraph.graphs.solver import chain_ordering, keyframe_rotations, keyframe_vectors, state_keys  # noqa: F401
from imugraph.graphs.velocity_block import VelocityBlock


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
        nRk = keyframe_rotations(values, self.block.n_keyframes)
        theta = self.theta_fixed if self.theta_fixed is not None else values.atVector(keys.CALIB)
        if self.block.with_field:      # the block reads the field perturbation of the Values it evaluates
            from imugraph.factors.field import field_key
            self.block.field_offsets = keyframe_vectors(values, field_key, self.block.n_keyframes)
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
    if ok.all():                      # every row: share the arrays instead of copying them
        return ChannelData(kf=pre.sample_kf, kRb=pre.kRb, values=values, sigma=np.asarray(sigma, float),
                           kernel=kernel, weight_floor=weight_floor)
    return ChannelData(kf=pre.sample_kf[ok], kRb=pre.kRb[ok], values=values[ok],
                       sigma=np.asarray(sigma, float), kernel=kernel,
                       weight_floor=None if weight_floor is None else weight_floor[ok])


@dataclass
class VelocityModel:
    """Linear acceleration modelled by keyframe velocities (imugraph.factors.velocity).

    sigma_v: stationary velocity std, m/s; tau_v: its correlation time, s; acc_rate_error: κ_a;
    v0: (K, 3) initial velocities (None: zero).
    """

    sigma_v: float = 0.5
    tau_v: float = 2.0
    acc_rate_error: float = 0.01
    kernel: Kernel = QUADRATIC
    v0: np.ndarray | None = None
    acc_bias: bool = True             # a sensor-frame accelerometer bias (random walk) in the state
    acc_bias_sigma0: float = 0.3      # m/s², prior std of the bias
    acc_bias_rw: float = 1e-3         # m/s²/√s, its random-walk density
    rest: np.ndarray | None = None    # (N,) samples at rest: keyframes whose interval rests get v = 0
    sigma_rest: float = 0.02          # m/s, std of that zero-velocity prior
    ar2: tuple | None = None          # (a_1, a_2, q): AR(2) process replacing (σ_v, τ_v) (calibration/velocity_ar2)
    position: tuple | None = None     # (σ_p m, τ_p s): bounded keyframe positions (velocity_block (P1)); None: none


@dataclass
class FieldModel:
    """Slowly varying nav-field perturbation (imugraph.factors.field): stationary std sigma (unit-field
    units, 0.01 ≈ 0.6°; scalar or (3,) per nav axis), correlation time tau, s; d0: (K, 3) initial values."""

    sigma: float | tuple = 0.015
    tau: float = 10.0
    d0: np.ndarray | None = None


@dataclass
class GyroMapModel:
    """Gyro scale/misalignment in the graph (imugraph.calibration.gyro_map): C (K−1, 3, 9) equivalent-bias
    maps at the current preintegration, e_now (9,) the Ê already applied, sigma_e prior std of E's entries."""

    C: np.ndarray
    e_now: np.ndarray
    sigma_e: float = 0.02


@dataclass
class Problem:
    graph: gtsam.NonlinearFactorGraph
    blocks: list
    values: gtsam.Values
    ordering: gtsam.Ordering
    block: MeasurementBlock
    ordering_keys: list
    velocity: VelocityBlock | None = None



def segment_dt(pre, n_seg: int) -> float:
    """The spacing of the gyro-bias segments' random walk: total keyframe time / number of segments (also the
    Δt of calibration/bias_process.py's EM step, which must match)."""
    return float(pre.dt.sum() / n_seg) if len(pre.dt) else 1.0

def build_problem(pre: Preintegration, b_acc: np.ndarray, b_mag: np.ndarray, noise: Noise, g: float,
                  nRk0: np.ndarray, bias0: np.ndarray, theta0: np.ndarray | None,
                  theta_prior_sigma: np.ndarray | None = None, bias_prior_sigma: float = 0.05,
                  acc_kernel: Kernel = QUADRATIC, mag_kernel: Kernel = QUADRATIC,
                  estimate_theta: bool = True, mag_weights=None,
                  bias_segment: np.ndarray | None = None, bias_rw_sigma: float = 0.0,
                  velocity: VelocityModel | None = None, dt: np.ndarray | None = None,
                  values0: gtsam.Values | None = None, field: FieldModel | None = None,
                  gyro_map: GyroMapModel | None = None) -> Problem:
    """Assemble the graph for a keyframe layout.

    Args:
        pre: preintegration (layout, ΔR, gyro factors' data); b_acc (N,3) m/s²; b_mag (N,3) raw field
        (NaN rows = no sample); noise: per-axis stds; g: gravity magnitude; nRk0 (K,3,3) initial
        orientations; bias0 (3,); theta0 (13,) calibration (initial or fixed);
        estimate_theta: False keeps θ fixed at theta0 (smoothing with a known calibration).
        bias_segment: (K−1,) bias segment of each keyframe interval (None: one constant bias); bias0 is
        then (S, 3); bias_rw_sigma: random-walk density of the bias, rad/s/√s, between segments
        (BetweenFactorVector with σ = bias_rw_sigma·√Δt_segment).
        velocity: model linear acceleration with keyframe velocities (needs dt (N,), the sample steps);
        the per-sample gravity factor then leaves the cost (its residuals are still reported).
        values0: initial Values already holding every state of this layout (R, B, V and θ keys, e.g. the
        previous solution of the same problem): used as they are instead of inserting nRk0, bias0, v0,
        theta0 (which still centre the priors).
        field: estimate a per-keyframe nav-field perturbation with a Gauss–Markov prior (FieldModel).
        gyro_map: estimate the gyro scale/misalignment E jointly (GyroMapModel; each gyro factor then reads
        its own bias key β_k, tied to the segment bias and E by graphs.gyro_map_block).
    """
    K = len(pre.kf_samples)
    graph = gtsam.NonlinearFactorGraph()
    seg = np.zeros(max(K - 1, 0), int) if bias_segment is None else np.asarray(bias_segment, int)
    bias0 = np.atleast_2d(np.asarray(bias0, float))
    n_seg = int(seg.max()) + 1 if len(seg) else 1
    if gyro_map is not None:
        from imugraph.graphs.gyro_map_block import E_KEY, GyroMapBlock, beta_key
    rk, vk = state_keys(keys.rot, K), state_keys(keys.vel, K)   # memoised key tuples (gtsam symbols cost ~1 µs)
    bk, fk = state_keys(keys.bias, n_seg), None
    qk = state_keys(beta_key, K - 1) if gyro_map is not None else None
    gyro_key = qk.__getitem__ if gyro_map is not None else (lambda i: bk[seg[i]])
    for f in ahrs_factors(pre, rk.__getitem__, gyro_key, noise.gyr):
        graph.add(f)
    fill = values0 is None
    values = gtsam.Values() if fill else values0
    for k in range(K if fill else 0):
        values.insert(rk[k], gtsam.Rot3(nRk0[k]))
    prior = gtsam.noiseModel.Isotropic.Sigma(3, bias_prior_sigma)
    seg_dt = segment_dt(pre, n_seg)
    rw = gtsam.noiseModel.Isotropic.Sigma(3, max(bias_rw_sigma, 1e-9) * np.sqrt(seg_dt))
    for i in range(n_seg):
        b_i = bias0[min(i, len(bias0) - 1)]
        if fill:
            values.insert(keys.bias(i), b_i)
        graph.add(gtsam.PriorFactorVector(keys.bias(i), b_i, prior))
        if i > 0:
            graph.add(gtsam.BetweenFactorVector(keys.bias(i - 1), keys.bias(i), np.zeros(3), rw))
    gblock = None
    if gyro_map is not None:         # β_k = b_s(k) and e = 0 at the start of every solve (Ê is in `pre`)
        gblock = GyroMapBlock(gyro_map.C, seg, keys.bias, np.asarray(gyro_map.e_now, float), gyro_map.sigma_e)
        b_seg = [values.atVector(bk[i]) for i in range(n_seg)]
        starts = [(key, b_seg[int(seg[k])]) for k, key in enumerate(qk)]
        for key, val in starts + [(E_KEY, np.zeros(9))]:
            if values.exists(key):
                values.update(key, val)
            else:
                values.insert(key, val)
    # interleave each bias segment after its keyframes: fill-in stays local
    vblock = None
    if velocity is not None:
        from imugraph.factors.gaps import GAP_ACC_WALK
        from imugraph.factors.velocity import bias_integrals, velocity_increments
        dv, sig_dv = velocity_increments(pre.kRb, pre.sample_kf, b_acc, dt, K, noise.acc,
                                         velocity.acc_rate_error,
                                         None if pre.gap_end is None else GAP_ACC_WALK)   # the gyro's gap setting
        B = bias_integrals(pre.kRb, pre.sample_kf, dt, K) if velocity.acc_bias else None
        rest_kf = None
        if velocity.rest is not None:
            moving = np.bincount(pre.sample_kf, weights=~np.asarray(velocity.rest, bool), minlength=K)
            rest_kf = moving == 0
        vblock = VelocityBlock(dv, sig_dv, pre.dt, g, velocity.sigma_v, velocity.tau_v, velocity.kernel,
                               B, velocity.acc_bias_sigma0, velocity.acc_bias_rw, rest_kf, velocity.sigma_rest,
                               velocity.ar2, position=velocity.position)
        if vblock.ar2 is not None:   # linear in the velocities: exact C++ factors, no Python per iteration
            graph.push_back(vblock.ar2_graph())
            vblock.ar2_in_graph = True
        v0 = np.zeros((K, vblock.state_dim)) if velocity.v0 is None else velocity.v0
        for k in range(K if fill else 0):
            values.insert(vk[k], np.asarray(v0[k], float))
        if vblock.position is not None:     # bounded positions (velocity_block (P1)): linear, C++ factors
            from imugraph.graphs.velocity_block import initial_positions, pos_key
            graph.push_back(vblock.position_graph())
            pk = state_keys(pos_key, K)
            if not values.exists(pk[0]):    # a start without positions (first solve, or a previous one without)
                p0 = initial_positions(keyframe_vectors(values, keys.vel, K), pre.dt)
                for k in range(K):
                    values.insert(pk[k], p0[k])
            # robust weights held for this solve, from the previous solution (a first solve: none yet, all 1)
            vblock.fixed_weights = (np.ones(K - 1) if fill else vblock.terms(*vblock._state(values))[2])
    fblock = None
    if field is not None and theta0 is not None:
        from imugraph.factors.field import field_key
        from imugraph.graphs.field_block import FieldBlock
        fblock = FieldBlock(pre.dt, field.sigma, field.tau)
        fk = state_keys(field_key, K)
        for k in range(K if fill else 0):
            values.insert(fk[k], np.zeros(3) if field.d0 is None else np.asarray(field.d0[k], float))
    order = []
    for k in range(K):
        order.append(rk[k])
        if vblock is not None:
            order.append(vk[k])
            if vblock.position is not None:
                order.append(pk[k])
        if fblock is not None:
            order.append(fk[k])
        if gblock is not None and k < K - 1:
            order.append(qk[k])
        if k < K - 1 and (k == K - 2 or seg[k + 1] != seg[k]):
            order.append(bk[seg[k]])
    if K == 1:
        order.append(keys.bias(0))
    global_keys: list = []
    use_theta = estimate_theta and theta0 is not None
    if use_theta:
        if fill:
            values.insert(keys.CALIB, np.asarray(theta0, float))
        sig = theta_prior_sigma if theta_prior_sigma is not None else np.full(THETA_DIM, 10.0)
        graph.add(gtsam.PriorFactorVector(keys.CALIB, np.asarray(theta0, float),
                                          gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sig, float))))
        global_keys.append(keys.CALIB)
    block = MeasurementBlock(
        n_keyframes=K,
        acc=channel(pre, b_acc, noise.acc, acc_kernel),
        mag=channel(pre, b_mag, noise.mag, mag_kernel, mag_weights) if theta0 is not None else None,
        g=g, use_theta=use_theta, use_acc=vblock is None, with_field=fblock is not None)
    adapter = BlockAdapter(block, None if use_theta else (None if theta0 is None else np.asarray(theta0)))
    if gblock is not None:
        global_keys.append(E_KEY)
    ordering = chain_ordering(order, global_keys)
    for lin in (fblock, gblock):     # linear priors/constraints: exact C++ factors, no Python per iteration
        if lin is not None:
            graph.push_back(lin.factors())
    blocks = [adapter] + ([vblock] if vblock is not None else [])
    return Problem(graph, blocks, values, ordering, block, order + global_keys, vblock)
