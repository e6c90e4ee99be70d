"""The nav-field perturbation d_k of the batch and stream models in `smooth_fixed` (its `field_sigma` option).

The batch model (imugraph.factors.field, calibration.ml with Options.field_sigma) and the stream
(imugraph.graphs.stream_field, stream_calstate) add a per-keyframe nav-frame vector d_k (unit-field units) to
the Earth field, with a first-order Gauss–Markov prior (stationary std σ_d per nav axis, correlation time τ_d):

    d_0 ~ N(0, σ_d²),  d_{k+1} = φ_k d_k + w_k,  φ_k = exp(−Δt_k/τ_d),  w_k ~ N(0, σ_d²(1 − φ_k²))        (1)

(exactly linear: C++ `LinearContainerFactor`s, `field_block.FieldBlock.factors`). Keyframe k's magnetometer
factor, with the calibration θ = (D, o, δ) held fixed, in either of the two averaged forms the code uses:

    "calibrated" (stream_field eq. 3, smooth_fixed's):  e_k = R_kᵀ(n + d_k) − m̄_k,
                  m̄_k = mean_j ΔR_kj D⁻¹(y_j − o),  Σ_k = Σ_j ΔR_kj D⁻¹ diag(σ_y²) D⁻ᵀ ΔR_kjᵀ / n_k²
    "raw" (stream_calstate eq. 1, the stream's default with θ as a state):
                  e_k = D M_k R_kᵀ(n + d_k) + o − ȳ_k,   M_k = mean_j ΔR_kjᵀ,  ȳ_k = mean_j y_j,  Σ_k = diag(σ_y²)/n_k

both e_k = A_k v_k − b_k with v_k = R_kᵀ(n + d_k) (A_k = I, b_k = m̄_k; A_k = D M_k, b_k = ȳ_k − o), and

    ∂e/∂ω = A_k [v_k]×,   ∂e/∂d_k = A_k R_kᵀ,   ∂e/∂(position) = 0                                         (2)

(right perturbation R_k Exp(ω), gtsam's Pose3 tangent [ω, v]), whitened by W_k (W_kᵀW_k = Σ_k⁻¹) and Huber-robust
as gtsam's `Robust` noise model (cost ρ(|r|), r = W_k e_k; linearised with √w(|r|) on A and b).

gtsam's wheel has no C++ factor of a rotation and a free nav vector (GTSAM_NOTES.md), and gtsam's C++ optimizers
would copy every Values into each Python callback (O(K²)): eq. (2) is a vectorised block (`FieldMagBlock`, one
numpy pass per iteration, K JacobianFactors) for the Python-driven Levenberg–Marquardt of `imugraph.graphs.solver`;
every other factor stays C++.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors.field import field_key
from imugraph.geometry import skew
from imugraph.graphs.cpp_velocity import pose_key
from imugraph.graphs.solver import cached_state, keyframe_vectors

__all__ = ["FieldMagBlock", "MAG_MODELS", "huber_cost", "keyframe_poses", "lm_solve", "mag_terms", "with_field_keys"]

MAG_MODELS = ("calibrated", "raw")
_UNIT3 = gtsam.noiseModel.Unit.Create(3)


def huber_cost(r_norm: np.ndarray, k: float | None) -> np.ndarray:
    """gtsam's Huber loss of whitened residual norms: |r|²/2 within k, k|r| − k²/2 beyond (None: quadratic)."""
    if not k:
        return 0.5 * r_norm**2
    return np.where(r_norm <= k, 0.5 * r_norm**2, k * r_norm - 0.5 * k * k)


def keyframe_poses(values: gtsam.Values, K: int) -> np.ndarray:
    """(K, 3, 3) rotations of the Pose3 keys X(0..K−1) (the only Pose3 values of the smoother's graph)."""
    return cached_state(values, ("pose3", K), lambda v: gtsam.utilities.extractPose3(v)[:K, :9].reshape(K, 3, 3))



class FieldMagBlock:
    """Eq. (2) for the keyframes `rows` (m,): A (m, 3, 3), b (m, 3), W (m, 3, 3); n_mag (3,) unit nav field;
    field: with d_k (False: v_k = R_kᵀ n, no d keys — the raw model without the perturbation); K keyframes."""

    def __init__(self, rows, A, b, W, n_mag, huber_k: float | None, field: bool, K: int):
        self.rows = np.asarray(rows, int)
        self.A, self.b, self.W = np.asarray(A, float), np.asarray(b, float), np.asarray(W, float)
        self.n, self.huber_k, self.field, self.K = np.asarray(n_mag, float), huber_k, bool(field), int(K)
        self._keys = [(pose_key(k), field_key(k)) for k in self.rows]

    def _state(self, values: gtsam.Values):
        R = keyframe_poses(values, self.K)[self.rows]
        nd = self.n + (keyframe_vectors(values, field_key, self.K)[self.rows] if self.field else np.zeros((len(R), 3)))
        v = np.einsum("kji,kj->ki", R, nd)                          # R_kᵀ(n + d_k)
        r = np.einsum("kij,kj->ki", self.W, np.einsum("kij,kj->ki", self.A, v) - self.b)
        return R, v, r

    def errors(self, values: gtsam.Values) -> np.ndarray:
        """(m, 3) unwhitened e_k."""
        R, v, _ = self._state(values)
        return np.einsum("kij,kj->ki", self.A, v) - self.b

    def cost(self, values: gtsam.Values) -> float:
        _, _, r = self._state(values)
        return float(huber_cost(np.linalg.norm(r, axis=1), self.huber_k).sum())

    def jacobians(self, values: gtsam.Values):
        """Whitened, Huber-weighted (H_pose (m, 3, 6), H_d (m, 3, 3), rhs (m, 3)) of eq. (2): A δ = rhs."""
        R, v, r = self._state(values)
        norm = np.linalg.norm(r, axis=1)
        k = self.huber_k
        sw = np.ones(len(norm)) if not k else np.sqrt(np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300)))
        WA = sw[:, None, None] * np.einsum("kij,kjl->kil", self.W, self.A)
        H_pose = np.zeros((len(r), 3, 6))
        H_pose[:, :, :3] = WA @ skew(v)
        H_d = WA @ np.transpose(R, (0, 2, 1))
        return H_pose, H_d, -sw[:, None] * r

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        H_pose, H_d, rhs = self.jacobians(values)
        gfg = gtsam.GaussianFactorGraph()
        if self.field:
            for (kp, kd), Hp, Hd, b in zip(self._keys, H_pose, H_d, rhs):
                gfg.push_back(gtsam.JacobianFactor(kp, Hp, kd, Hd, b, _UNIT3))
        else:
            for (kp, _), Hp, b in zip(self._keys, H_pose, rhs):
                gfg.push_back(gtsam.JacobianFactor(kp, Hp, b, _UNIT3))
        return gfg


def mag_terms(model: str, pre, y: np.ndarray, cal, sig_y: np.ndarray, valid: np.ndarray, K: int):
    """(rows, A, b, W) of eq. (2) for every keyframe with a valid field sample. y (N, 3) raw field (windows
    applied), valid (N,); pre: the preintegration (kRb = ΔR_kj, sample_kf); sig_y (3,): one raw sample's σ."""
    skf, kRb = pre.sample_kf[valid], pre.kRb[valid]
    n_k = np.bincount(skf, minlength=K)
    rows = np.flatnonzero(n_k)
    n = n_k[rows].astype(float)
    D_inv = np.linalg.inv(cal.D)
    if model == "calibrated":
        m = (y[valid] - cal.o) @ D_inv.T
        s = np.zeros((K, 3)); np.add.at(s, skf, np.einsum("mij,mj->mi", kRb, m))
        S_m = D_inv @ np.diag(sig_y**2) @ D_inv.T
        cov = np.zeros((K, 3, 3)); np.add.at(cov, skf, kRb @ S_m @ np.transpose(kRb, (0, 2, 1)))
        cov = cov[rows] / n[:, None, None] ** 2
        # W = L⁻¹ with Σ = L Lᵀ: (L⁻¹)ᵀ L⁻¹ = Σ⁻¹
        W = np.linalg.inv(np.linalg.cholesky(cov))
        return rows, np.broadcast_to(np.eye(3), (len(rows), 3, 3)).copy(), s[rows] / n[:, None], W
    if model == "raw":
        sR = np.zeros((K, 3, 3)); np.add.at(sR, skf, np.transpose(kRb, (0, 2, 1)))
        sy = np.zeros((K, 3)); np.add.at(sy, skf, y[valid])
        A = cal.D @ (sR[rows] / n[:, None, None])                   # D M_k
        W = np.sqrt(n)[:, None, None] * np.diag(1.0 / np.asarray(sig_y, float))[None]
        return rows, A, sy[rows] / n[:, None] - cal.o, W
    raise ValueError(f"mag_model: found {model!r}, expected one of {MAG_MODELS}")


def with_field_keys(ordering: gtsam.Ordering, vel_key, K: int, field: bool) -> gtsam.Ordering:
    """The velocity graph's chain ordering with d_k right after keyframe k's velocity (field True)."""
    out = gtsam.Ordering()
    vel = {vel_key(k): k for k in range(K)}
    for i in range(ordering.size()):
        key = ordering.at(i)
        out.push_back(key)
        if field and key in vel:
            out.push_back(field_key(vel[key]))
    return out


def lm_solve(graph: gtsam.NonlinearFactorGraph, block: FieldMagBlock, values: gtsam.Values, ordering: gtsam.Ordering,
             max_iterations: int, rotation_tol: float, relative_tol: float = 1e-6) -> gtsam.Values:
    """Levenberg–Marquardt driven from Python (graphs.solver's loop: C++ graph linearised by gtsam, the block by numpy,
    √λ I damping, sequential elimination in `ordering`), stopped as smooth_fixed's C++ solve is: when no keyframe
    orientation moves by more than `rotation_tol` (rad) in an accepted step, or the cost decreases by less than
    relative_tol of itself. Why not graphs.solver.optimize alone: the Huber velocity rows give the cost a long tail in
    which the orientations no longer move (BROAD 07: 26 iterations, 2.4 s CPU, the last 20 changing the cost by 0.01 %)."""
    from imugraph.graphs.solver import _damping, _solve, total_cost

    x = gtsam.Values(values)
    cost, lam, K = total_cost(graph, [block], x), 1e-4, block.K
    key_dims = tuple(x.dims().items())
    prev = gtsam.utilities.extractPose3(x)[:K, :9].reshape(K, 3, 3)
    for _ in range(int(max_iterations)):
        gfg = graph.linearize(x)
        gfg.push_back(block.linearize(x))
        rejected = 0
        while True:
            sys_ = gtsam.GaussianFactorGraph()
            sys_.push_back(gfg)
            sys_.push_back(_damping(key_dims, lam))
            try:
                x_new = x.retract(_solve(sys_, ordering, "sequential"))
                new_cost = total_cost(graph, [block], x_new)
            except RuntimeError:            # indeterminate: damp harder
                new_cost = float("inf")
            if new_cost <= cost:
                break
            lam *= 10.0
            rejected += 1
            if lam > 1e8:
                return x                    # no descent: at a minimum within numerical precision
        cur = gtsam.utilities.extractPose3(x_new)[:K, :9].reshape(K, 3, 3)
        moved = float(np.arccos(np.clip((np.einsum("kij,kij->k", prev, cur).min() - 1.0) / 2.0, -1.0, 1.0)))
        decrease = cost - new_cost
        x, cost, prev, lam = x_new, new_cost, cur, max(lam / 10.0, 1e-12)
        # a step shortened by rejected (damped) tries is not convergence: only an undamped small step stops
        if (moved < rotation_tol and rejected == 0) or decrease <= relative_tol * max(cost, 1e-300):
            break
    return x
