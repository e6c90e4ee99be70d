"""The velocity chain of the single-IMU graph as one vectorised block (see imugraph.factors.velocity).

Per keyframe interval k one JacobianFactor on (R_k, v_k, v_{k+1}) stacks the accelerometer increment
(robust-weighted) and the Gauss–Markov prior; one more factor holds v_0 ~ N(0, σ_v²):

    [ w^½ J_R/σ_e    −w^½ I/σ_e     w^½ I/σ_e ] [ξ_k ]      [ −w^½ e_k/σ_e               ]
    [   0            −φ_k I/σ_w       I/σ_w   ] [δv_k ]  =  [ −(v_{k+1} − φ_k v_k)/σ_w    ]
                                                [δv_k+1]
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.robust import QUADRATIC, Kernel
from imugraph.factors.velocity import gauss_markov, velocity_model

_UNIT6 = gtsam.noiseModel.Unit.Create(6)
_UNIT3 = gtsam.noiseModel.Unit.Create(3)


@dataclass
class VelocityBlock:
    """Accelerometer increments Δv_k (K−1, 3) with error std (K−1,), interval lengths, and the prior."""

    dv: np.ndarray
    sigma_dv: np.ndarray
    dt_k: np.ndarray
    g: float
    sigma_v: float = 0.5
    tau_v: float = 2.0
    kernel: Kernel = QUADRATIC

    @property
    def n_keyframes(self) -> int:
        return len(self.dv) + 1

    def _state(self, values: gtsam.Values):
        K = self.n_keyframes
        nRk = np.stack([values.atRot3(keys.rot(k)).matrix() for k in range(K)])
        v = np.stack([values.atVector(keys.vel(k)) for k in range(K)])
        return nRk, v

    def terms(self, nRk: np.ndarray, v: np.ndarray):
        """Whitened increment residuals r (K−1, 3), Jacobians, robust weights, and the prior residuals."""
        e, J_R = velocity_model(nRk, v, self.dv, self.dt_k, self.g)
        r = e / self.sigma_dv[:, None]
        w = self.kernel.weight(np.linalg.norm(r, axis=1))
        phi, sigma_w = gauss_markov(self.dt_k, self.sigma_v, self.tau_v)
        gm = (v[1:] - phi[:, None] * v[:-1]) / sigma_w[:, None]
        return r, J_R, w, phi, sigma_w, gm

    def cost_at(self, nRk: np.ndarray, v: np.ndarray) -> float:
        r, _, _, _, _, gm = self.terms(nRk, v)
        return float(self.kernel.rho(np.linalg.norm(r, axis=1)).sum()
                     + 0.5 * np.sum(gm**2) + 0.5 * np.sum((v[0] / self.sigma_v) ** 2))

    def cost(self, values: gtsam.Values) -> float:
        return self.cost_at(*self._state(values))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        nRk, v = self._state(values)
        r, J_R, w, phi, sigma_w, gm = self.terms(nRk, v)
        sw = np.sqrt(w) / self.sigma_dv                       # (K−1,) row scale of the increment rows
        eye = np.eye(3)
        gfg = gtsam.GaussianFactorGraph()
        gfg.push_back(gtsam.JacobianFactor(keys.vel(0), eye / self.sigma_v, -v[0] / self.sigma_v, _UNIT3))
        zero = np.zeros((3, 3))
        for k in range(len(r)):
            A_R = np.vstack([J_R[k] * sw[k], zero])
            A_v0 = np.vstack([-eye * sw[k], -phi[k] / sigma_w[k] * eye])
            A_v1 = np.vstack([eye * sw[k], eye / sigma_w[k]])
            b = -np.concatenate([r[k] * np.sqrt(w[k]), gm[k]])
            gfg.push_back(gtsam.JacobianFactor(keys.rot(k), A_R, keys.vel(k), A_v0, keys.vel(k + 1), A_v1,
                                               b, _UNIT6))
        return gfg
