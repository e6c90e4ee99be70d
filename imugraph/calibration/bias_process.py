"""Maximum-likelihood density of the gyro-bias random walk inside the ML loop (EM).

The calibration graph (imugraph.graphs.single_imu.build_problem) holds one gyro bias b_m per segment of
`Options.bias_segment_s` seconds, joined by a random walk with density q (rad/s/√s, IEEE Std 952's "rate
random walk" of the gyro):

    b_{m+1} = b_m + w_m,      w_m ~ N(0, q² Δt I₃),      Δt = the segment length the graph uses
                                                         (total keyframe time / number of segments)

Instead of fixing q (Options.bias_rw), each ML round may re-estimate it from the round's solution, as Σω,
Σa, Σm and the velocity process (calibration/velocity_process.py) are re-estimated. This is
expectation-maximisation for a linear state-space model (Shumway & Stoffer 1982). The M-step maximises the
expected log-density of the random-walk terms under the posterior of the biases,

    −E log p(b | q) = (3(S−1)/2) ln(q² Δt) + Σ_m E|b_{m+1} − b_m|² / (2 q² Δt)       (+ const)

whose minimiser is closed form:

    q̂² = Σ_m E|b_{m+1} − b_m|² / (3 (S−1) Δt)                                       (B1)

    E|b_{m+1} − b_m|² = |μ_{m+1} − μ_m|² + tr P_{m+1} + tr P_m − 2 tr C_m              (B2)

with μ_m the posterior means of the segment biases, P_m = Cov(b_m) and C_m = Cov(b_m, b_{m+1}) their
posterior (marginal) covariances. Without the covariances the step would use the means alone, which the
random walk shrinks toward each other, and EM would drift toward a stiffer bias.

E-step at the round's linearisation (Laplace approximation): every factor except the random walk is
linearised at the round's solution and every state except the biases marginalised (in the problem's own
chain order), leaving the biases' information H₀ (3S × 3S) and vector η₀ about the linearisation point μ⁰.
The random walk adds Λ(q) = (DᵀD ⊗ I₃)/(q² Δt) (D: the (S−1) × S first difference), so for any q

    H(q) = H₀ + Λ(q),    μ(q) = μ⁰ + H(q)⁻¹ (η₀ − Λ(q) μ⁰),    Cov(b) = H(q)⁻¹              (B3)

without touching the rest of the graph: EM (B3 → B2 → B1) is iterated to its fixed point on this
linearisation in each round (one EM step per round converges slowly when the bias is weakly observed,
each step moving q by a fraction of the way), and the ML rounds re-linearise.

q̂ is held inside RW_BOUNDS (physical limits of a MEMS gyro, below). The ML loop's convergence test sees

    |ln(max(q̂, q_irr) / max(q, q_irr))|,   q_irr = 0.1 · √(median_i (H₀⁻¹)_ii / Δt)                  (B4)

below q_irr one step of the walk moves a segment's bias by less than a tenth of what the data resolve of it,
so the walk is a constant bias to them and EM's slow creep toward the lower bound (BROAD 04, 07, 24: q̂ →
3e-6 over 8 rounds) is not a change of the model.
"""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from imugraph.graphs.single_imu import segment_dt      # the graph's own segment spacing (must match)
from imugraph import keys

# Physical limits of q, rad/s/√s (order-of-magnitude choices, not datasheet values; the rate random walk K
# of IEEE Std 952's Allan-variance model). Lower: 1e-6 moves the bias by 6e-5 rad/s (0.003 °/s) in an hour —
# steadier than a MEMS gyro's in-run bias (datasheets quote its instability in °/h, and its temperature
# drift dominates over minutes). Upper: 5e-3 moves the bias by 0.29 °/s in one second and 0.64 °/s over a
# 5 s segment — far beyond a MEMS gyro's in-run drift at steady temperature; a larger value would let the
# bias absorb the motion (turns about directions the magnetometer and accelerometer see only weakly).
RW_BOUNDS = (1e-6, 5e-3)


def bias_keys(n_seg: int) -> list[int]:
    """gtsam keys of the S segment biases."""
    return [keys.bias(i) for i in range(n_seg)]


def _is_random_walk(factor, bias_set: set) -> bool:
    keys_ = list(factor.keys())
    return len(keys_) == 2 and keys_[0] in bias_set and keys_[1] in bias_set


def bias_information(prob, values: gtsam.Values, n_seg: int) -> tuple[np.ndarray, np.ndarray]:
    """(H₀ (3S, 3S), η₀ (3S,)): the segment biases' information and information vector from every factor of
    the problem except the random walk between them (B3), linearised at `values`, every other state
    marginalised (eliminated first in the problem's chain order). Flat index 3m + i: axis i of b_m."""
    bk = bias_keys(n_seg)
    bias_set = set(bk)
    graph = gtsam.NonlinearFactorGraph()
    for i in range(prob.graph.size()):
        f = prob.graph.at(i)
        if f is not None and not _is_random_walk(f, bias_set):
            graph.push_back(f)
    gfg = graph.linearize(values)
    for b in prob.blocks:
        gfg.push_back(b.linearize(values))
    others = [k for k in prob.ordering_keys if k not in bias_set]
    if others:
        bn = gfg.marginalMultifrontalBayesNet(gtsam.Ordering(bk), gtsam.Ordering(others))
        gfg = gtsam.GaussianFactorGraph()
        gfg.push_back(bn)
    aug = gfg.augmentedHessian(gtsam.Ordering(bk))          # [[AᵀA, Aᵀb], [bᵀA, bᵀb]]
    H0 = aug[:-1, :-1]
    return 0.5 * (H0 + H0.T), aug[:-1, -1].copy()


def random_walk_information(n_seg: int, q: float, seg_dt: float) -> np.ndarray:
    """Λ(q) = (DᵀD ⊗ I₃)/(q² Δt) (B3): the random walk's information on the flat segment biases."""
    D = np.diff(np.eye(n_seg), axis=0)
    return np.kron(D.T @ D, np.eye(3)) / (q * q * seg_dt)


def posterior(H0: np.ndarray, eta0: np.ndarray, mu0: np.ndarray, q: float, seg_dt: float):
    """(μ (S, 3), P (S, 3, 3), C (S−1, 3, 3)) of the segment biases with random-walk density q (B3)."""
    S = len(mu0)
    Lam = random_walk_information(S, q, seg_dt)
    H = H0 + Lam
    cov = np.linalg.inv(H)
    cov = 0.5 * (cov + cov.T)
    mu = np.asarray(mu0, float) + (cov @ (eta0 - Lam @ np.ravel(mu0))).reshape(S, 3)
    blocks = cov.reshape(S, 3, S, 3).transpose(0, 2, 1, 3)       # blocks[m, n] = Cov(b_m, b_n)
    idx = np.arange(S)
    return mu, blocks[idx, idx], blocks[idx[:-1], idx[1:]]


def fit_rw(H0: np.ndarray, eta0: np.ndarray, mu0: np.ndarray, q0: float, seg_dt: float,
           bounds: tuple = RW_BOUNDS, max_iter: int = 300, tol: float = 1e-4) -> tuple[float, int]:
    """EM (B3 → B2 → B1) from q0 to its fixed point on one linearisation: (q̂, iterations). Stops when
    |ln q| moves less than tol, or after max_iter steps (sublinear near a bound)."""
    q = float(np.clip(q0, *bounds))
    for it in range(1, max_iter + 1):
        mu, P, C = posterior(H0, eta0, mu0, q, seg_dt)
        q_new = em_rw_density(increment_moments(mu, P, C), seg_dt, bounds)
        done = abs(np.log(q_new / q)) < tol
        q = q_new
        if done:
            break
    return q, it


def increment_moments(mu: np.ndarray, P: np.ndarray | None = None, C: np.ndarray | None = None) -> np.ndarray:
    """(S−1,) E|b_{m+1} − b_m|² (B2) from means mu (S, 3) and covariances P (S, 3, 3), C (S−1, 3, 3)
    (None: the means alone)."""
    mu = np.asarray(mu, float)
    e = np.sum(np.diff(mu, axis=0) ** 2, axis=1)
    if P is not None:
        trP = np.trace(np.asarray(P, float), axis1=1, axis2=2)
        e = e + trP[1:] + trP[:-1]
    if C is not None:
        e = e - 2.0 * np.trace(np.asarray(C, float), axis1=1, axis2=2)
    return e


def em_rw_density(e_inc: np.ndarray, seg_dt: float, bounds: tuple = RW_BOUNDS) -> float:
    """q̂ (B1) from the expected squared increments e_inc (S−1,) of segments seg_dt seconds apart, held in bounds."""
    e_inc = np.asarray(e_inc, float)
    q2 = float(np.sum(e_inc)) / (3.0 * len(e_inc) * seg_dt)                  # (B1)
    return float(np.clip(np.sqrt(max(q2, 0.0)), *bounds))


def update_bias_rw(rw: float, prob, values: gtsam.Values, pre, n_seg: int,
                   record: dict | None = None) -> tuple[float, float]:
    """EM for the bias random-walk density on a round's solution (`fit_rw` from the current q): (q̂, change)
    — the change (B4) for the ML loop's convergence test. With a single segment, or an indeterminate linearisation,
    q is kept.

    Args:
        rw: the current q, rad/s/√s; prob, values: the round's Problem and solution; pre: its preintegration
        (keyframe intervals); n_seg: number of bias segments; record: history entry to note q̂ in.
    """
    if n_seg < 2:
        return float(rw), 0.0
    mu0 = np.stack([values.atVector(k) for k in bias_keys(n_seg)])
    dt = segment_dt(pre, n_seg)
    try:
        H0, eta0 = bias_information(prob, values, n_seg)
        q, iters = fit_rw(H0, eta0, mu0, rw, dt)
        q_irr = 0.1 * float(np.sqrt(np.median(np.diag(np.linalg.inv(H0))) / dt))        # (B4)
    except (RuntimeError, np.linalg.LinAlgError):
        return float(rw), 0.0
    if record is not None:
        record["bias_rw"], record["bias_rw_em_iterations"], record["bias_rw_irrelevant"] = q, iters, q_irr
    return q, abs(float(np.log(max(q, q_irr) / max(rw, q_irr))))


def em_bias_rw(opt, prob, values: gtsam.Values, pre, n_seg: int, record: dict, change: float):
    """The ML loop's hook (calibration.ml.ml_rounds): Options with bias_rw = q̂ for the next solve, and the
    round's convergence measure raised to the change of q (B4) where larger."""
    q, dq = update_bias_rw(opt.bias_rw, prob, values, pre, n_seg, record)
    return replace(opt, bias_rw=q), max(change, dq)
