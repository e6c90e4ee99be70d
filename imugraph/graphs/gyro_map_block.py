"""Gyro scale/misalignment E in the single-IMU graph (imugraph.calibration.gyro_map), as one linear block.

Each gyro factor k reads its own bias key β_k; this block ties them to the segment biases b_s and to
e = vec E (relative to the Ê the gyro was preintegrated with) by linear constraints, and holds the prior
on the total Ê + e:

    (β_k − b_s(k) − C_k e)/σ_c = 0,        (Ê + e)/σ_e ~ N(0, I),      S(Ê + e)/σ_rot ~ N(0, I)

S e = the rotation vector of E's antisymmetric part, (E − Eᵀ)/2 = [S e]×: a rotation of the gyro axes
against the accelerometer's, which only the (weak) accelerometer constraint sees — unconstrained it ran
to 5° on BROAD 04 — so it gets a tight prior σ_rot; the symmetric part (scale, non-orthogonality) keeps σ_e.

Both are linear, so the JacobianFactors are exact (three keys: β_k, b_s(k), e), and they can be handed to
GTSAM once as C++ `LinearContainerFactor`s linearised at zero (`GyroMapBlock.factors`), which GTSAM
re-linearises itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph.graphs.solver import keyframe_vectors, state_keys

E_KEY = gtsam.symbol("e", 0)
# S: e = vec E (row-major) → the axial vector of (E − Eᵀ)/2: ((E21 − E12), (E02 − E20), (E10 − E01))/2
_ANTI = np.zeros((3, 9))
for _r, (_i, _j) in enumerate(((2, 1), (0, 2), (1, 0))):
    _ANTI[_r, 3 * _i + _j] += 0.5
    _ANTI[_r, 3 * _j + _i] -= 0.5


def beta_key(k: int) -> int:
    """Key of gyro interval k's effective bias β_k (Vector3)."""
    return gtsam.symbol("q", int(k))


def without_map_keys(values: gtsam.Values) -> gtsam.Values:
    """values without the β_k and e keys (a copy; values itself when it holds none), for a graph built
    without the gyro-map block: variables with no factor are not in its ordering, and eliminating with
    them fails (the solver then saw an indeterminate system at every λ and returned its start)."""
    if not values.exists(E_KEY):
        return values
    out = gtsam.Values(values)
    q = ord("q")
    for key in values.keys():
        if key == E_KEY or gtsam.Symbol(key).chr() == q:
            out.erase(key)
    return out


@dataclass
class GyroMapBlock:
    """C: (K−1, 3, 9) equivalent-bias maps; seg: (K−1,) bias segment of each interval; bias_key: i → key;
    e_now: (9,) the Ê already applied to the gyro; sigma_e: prior std of E's entries; sigma_c: constraint std."""

    C: np.ndarray
    seg: np.ndarray
    bias_key: object
    e_now: np.ndarray
    sigma_e: float = 0.02
    sigma_c: float = 1e-6
    sigma_rot: float = 1e-3

    def _state(self, values: gtsam.Values):
        n = len(self.C)
        n_seg = int(self.seg.max()) + 1 if n else 1
        beta = keyframe_vectors(values, beta_key, n).reshape(n, 3)       # cached per Values
        b = keyframe_vectors(values, self.bias_key, n_seg).reshape(n_seg, 3)
        return beta, b, values.atVector(E_KEY)

    def residuals(self, values: gtsam.Values):
        beta, b, e = self._state(values)
        con = (beta - b[self.seg] - np.einsum("kij,j->ki", self.C, e)) / self.sigma_c
        tot = self.e_now + e
        return con, np.r_[tot / self.sigma_e, _ANTI @ tot / self.sigma_rot]

    def cost(self, values: gtsam.Values) -> float:
        con, pri = self.residuals(values)
        return 0.5 * float(np.sum(con**2) + np.sum(pri**2))

    def _jacobians(self, con: np.ndarray, pri: np.ndarray) -> gtsam.GaussianFactorGraph:
        """The JacobianFactors A δ = −r for residuals con (K−1, 3), pri (12,) (A is constant)."""
        gfg = gtsam.GaussianFactorGraph()
        unit3 = gtsam.noiseModel.Unit.Create(3)
        eye = np.eye(3) / self.sigma_c
        C = -self.C / self.sigma_c
        bk = state_keys(beta_key, len(con))
        for k in range(len(con)):
            gfg.push_back(gtsam.JacobianFactor(bk[k], eye, self.bias_key(int(self.seg[k])), -eye,
                                               E_KEY, C[k], -con[k], unit3))
        A = np.r_[np.eye(9) / self.sigma_e, _ANTI / self.sigma_rot]
        gfg.push_back(gtsam.JacobianFactor(E_KEY, A, -pri, gtsam.noiseModel.Unit.Create(12)))
        return gfg

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        return self._jacobians(*self.residuals(values))

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """The block as C++ nonlinear factors (exact: it is linear), for the graph itself instead of the
        solver's block list: LinearContainerFactors of its Jacobians at β = b = e = 0."""
        n = len(self.C)
        n_seg = int(self.seg.max()) + 1 if n else 1
        zero = gtsam.Values()
        for key in list(state_keys(beta_key, n)) + [self.bias_key(i) for i in range(n_seg)]:
            zero.insert(key, np.zeros(3))
        zero.insert(E_KEY, np.zeros(9))
        con = np.zeros((n, 3))
        pri = np.r_[self.e_now / self.sigma_e, _ANTI @ self.e_now / self.sigma_rot]
        return gtsam.LinearContainerFactor.ConvertLinearGraph(self._jacobians(con, pri), zero)
