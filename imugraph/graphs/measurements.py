"""All accelerometer and magnetometer samples of a session as one vectorised block of the graph.

The block evaluates the models of `imugraph.factors.accelerometer` and `imugraph.factors.magnetometer`
for every sample at once (numpy), applies per-sample robust weights (`imugraph.factors.robust`), and
hands GTSAM one `HessianFactor` per keyframe on (R_k, θ):

    G11 = Σ_j w_j J_Rᵀ J_R,  G12 = Σ_j w_j J_Rᵀ J_θ,  G22 = Σ_j w_j J_θᵀ J_θ,
    g1  = −Σ_j w_j J_Rᵀ r_j, g2  = −Σ_j w_j J_θᵀ r_j, f = Σ_j w_j |r_j|²

(whitened residuals r_j and Jacobians J; GTSAM's HessianFactor error is ½(f − 2xᵀg + xᵀGx)).
This is the same linearisation GTSAM would compute from one CustomFactor per keyframe, at a fraction
of the cost: no Python callback per factor (see GTSAM_NOTES.md: callbacks dominate batch cost).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.accelerometer import accelerometer_model
from imugraph.factors.magnetometer import magnetometer_model
from imugraph.factors.robust import QUADRATIC, Kernel
from imugraph.factors.theta import THETA_DIM


@dataclass
class ChannelData:
    """Samples of one channel attached to keyframes: rows of `values` with their keyframe and ΔR."""

    kf: np.ndarray        # (M,) keyframe index of each sample
    kRb: np.ndarray       # (M, 3, 3)
    values: np.ndarray    # (M, 3) measurements
    sigma: np.ndarray     # (3,) per-axis std
    kernel: Kernel = QUADRATIC
    weight_floor: np.ndarray | None = None   # optional fixed extra weights (M,) in [0, 1]


@dataclass
class MeasurementBlock:
    """The accelerometer and magnetometer channels of one session, for K keyframes."""

    n_keyframes: int
    acc: ChannelData | None
    mag: ChannelData | None
    g: float = 9.81
    use_theta: bool = True
    use_acc: bool = True        # False: acc residuals are reported but not in the cost (velocity model)
    _last: dict = field(default_factory=dict, repr=False)

    # ---- residuals -------------------------------------------------------------------------------
    def residuals(self, nRk: np.ndarray, theta: np.ndarray, in_cost_only: bool = False) -> dict:
        """Whitened residuals per channel: {"acc": (M, 3), "mag": (M, 3)} at keyframe rotations nRk
        (in_cost_only: skip a channel that is reported but not in the cost)."""
        out = {}
        if self.acc is not None and (self.use_acc or not in_cost_only):
            e, _ = accelerometer_model(self.acc.kRb, nRk[self.acc.kf], self.acc.values, self.g)
            out["acc"] = e / self.acc.sigma
        if self.mag is not None:
            e, _, _ = magnetometer_model(self.mag.kRb, nRk[self.mag.kf], theta, self.mag.values)
            out["mag"] = e / self.mag.sigma
        return out

    def cost(self, nRk: np.ndarray, theta: np.ndarray) -> float:
        """Σ ρ(|r_j|) over both channels (GTSAM's ½|r|² for the quadratic kernel)."""
        total = 0.0
        for name, r in self.residuals(nRk, theta, in_cost_only=True).items():
            ch = getattr(self, name)
            rho = ch.kernel.rho(np.linalg.norm(r, axis=1))
            if ch.weight_floor is not None:
                rho = rho * ch.weight_floor
            total += float(rho.sum())
        return total

    # ---- linearisation ---------------------------------------------------------------------------
    def _channel_terms(self, ch: ChannelData, e, J_rot, J_theta):
        r = e / ch.sigma
        s = np.linalg.norm(r, axis=1)
        w = ch.kernel.weight(s)
        if ch.weight_floor is not None:
            w = w * ch.weight_floor
        sw = np.sqrt(w)[:, None, None]
        A = J_rot * (sw / ch.sigma[None, :, None])            # weighted, whitened Jacobian rows
        rw = r * sw[:, :, 0]
        At = np.transpose(A, (0, 2, 1))
        K = self.n_keyframes
        G11 = _sum_by(ch.kf, At @ A, K)
        g1 = _sum_by(ch.kf, -(At @ rw[:, :, None])[:, :, 0], K)
        f = _sum_by(ch.kf, np.sum(rw * rw, axis=1), K)
        if J_theta is None:
            return G11, None, None, g1, None, f
        T = J_theta * (sw / ch.sigma[None, :, None])
        Tt = np.transpose(T, (0, 2, 1))
        G12 = _sum_by(ch.kf, At @ T, K)
        G22 = _sum_by(ch.kf, Tt @ T, K)
        g2 = _sum_by(ch.kf, -(Tt @ rw[:, :, None])[:, :, 0], K)
        return G11, G12, G22, g1, g2, f

    def hessian_blocks(self, nRk: np.ndarray, theta: np.ndarray):
        """Per-keyframe blocks (G11 (K,3,3), G12 (K,3,13), G22 (K,13,13), g1 (K,3), g2 (K,13), f (K,))."""
        K = self.n_keyframes
        G11 = np.zeros((K, 3, 3)); g1 = np.zeros((K, 3)); f = np.zeros(K)
        G12 = np.zeros((K, 3, THETA_DIM)); G22 = np.zeros((K, THETA_DIM, THETA_DIM)); g2 = np.zeros((K, THETA_DIM))
        if self.acc is not None and self.use_acc:
            e, J = accelerometer_model(self.acc.kRb, nRk[self.acc.kf], self.acc.values, self.g)
            a11, _, _, a1, _, af = self._channel_terms(self.acc, e, J, None)
            G11 += a11; g1 += a1; f += af
        if self.mag is not None:
            e, J_rot, J_theta = magnetometer_model(self.mag.kRb, nRk[self.mag.kf], theta, self.mag.values)
            m11, m12, m22, m1, m2, mf = self._channel_terms(self.mag, e, J_rot, J_theta if self.use_theta else None)
            G11 += m11; g1 += m1; f += mf
            if self.use_theta:
                G12 += m12; G22 += m22; g2 += m2
        return G11, G12, G22, g1, g2, f

    def linear_factors(self, nRk: np.ndarray, theta: np.ndarray) -> gtsam.GaussianFactorGraph:
        """A GaussianFactorGraph with one HessianFactor per keyframe (two keys when θ is estimated)."""
        G11, G12, G22, g1, g2, f = self.hessian_blocks(nRk, theta)
        gfg = gtsam.GaussianFactorGraph()
        two = self.use_theta and self.mag is not None
        for k in range(self.n_keyframes):
            if two:
                gfg.push_back(gtsam.HessianFactor(keys.rot(k), keys.CALIB, G11[k], G12[k], g1[k],
                                                  G22[k], g2[k], f[k]))
            else:
                gfg.push_back(gtsam.HessianFactor(keys.rot(k), G11[k], g1[k], f[k]))
        return gfg


def _sum_by(index: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of x (M, …) into n bins by index (M,) (index need not be sorted)."""
    out = np.zeros((n,) + x.shape[1:])
    np.add.at(out, index, x) if not _is_sorted(index) else _reduce_sorted(out, index, x)
    return out


def _is_sorted(index: np.ndarray) -> bool:
    return bool(np.all(index[1:] >= index[:-1])) if len(index) > 1 else True


def _reduce_sorted(out: np.ndarray, index: np.ndarray, x: np.ndarray) -> None:
    if len(index) == 0:
        return
    starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
    out[index[starts]] = np.add.reduceat(x, starts, axis=0)
