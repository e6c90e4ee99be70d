"""The Gauss–Markov prior of the field perturbation d_k (imugraph.factors.field) as one linear block.

The prior is linear in d, so its JacobianFactors are exact:

    [ I/σ_d ] d_0 = −d_0/σ_d (at the linearisation point),   [ −φ_k I/σ_w,k   I/σ_w,k ] [δd_k; δd_{k+1}]
                                                               = −(d_{k+1} − φ_k d_k)/σ_w,k

Being exact, they can also be handed to GTSAM once, as C++ `LinearContainerFactor`s linearised at d = 0
(`FieldBlock.factors`): GTSAM then re-linearises them itself (b = −A·d), with no Python per iteration.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph.factors.field import field_key, field_prior_terms, field_sigmas
from imugraph.graphs.solver import keyframe_vectors, state_keys


_LAST_FACTORS: dict = {}        # tag (dt_k, σ_d, τ_d) → the prior's factors (FieldBlock.factors)


@dataclass
class FieldBlock:
    """GM prior on K keyframe field perturbations; dt_k (K−1,) interval lengths, s."""

    dt_k: np.ndarray
    sigma_d: float | np.ndarray      # scalar or (3,) per nav axis
    tau_d: float

    @property
    def n_keyframes(self) -> int:
        return len(self.dt_k) + 1

    def offsets(self, values: gtsam.Values) -> np.ndarray:
        """(K, 3) d_k from values."""
        return keyframe_vectors(values, field_key, self.n_keyframes)

    def cost_at(self, d: np.ndarray) -> float:
        start, steps, _, _ = field_prior_terms(d, self.dt_k, self.sigma_d, self.tau_d)
        return 0.5 * float(np.sum(start**2) + np.sum(steps**2))

    def cost(self, values: gtsam.Values) -> float:
        return self.cost_at(self.offsets(values))

    def _jacobians(self, d: np.ndarray) -> gtsam.GaussianFactorGraph:
        """The prior's JacobianFactors at d (K, 3): A δ = −r(d) (A does not depend on d)."""
        start, steps, phi, sigma_w = field_prior_terms(d, self.dt_k, self.sigma_d, self.tau_d)
        unit = gtsam.noiseModel.Unit.Create(3)
        gfg = gtsam.GaussianFactorGraph()
        sig = field_sigmas(self.sigma_d)
        fk = state_keys(field_key, self.n_keyframes)
        eye = np.eye(3)
        A0 = -(phi[:, None] / sigma_w)[:, :, None] * eye       # diag(−φ_k/σ_w,k) (K−1, 3, 3)
        A1 = (1.0 / sigma_w)[:, :, None] * eye                 # diag(1/σ_w,k)
        gfg.push_back(gtsam.JacobianFactor(fk[0], np.diag(1.0 / sig), -start, unit))
        for k in range(len(steps)):
            gfg.push_back(gtsam.JacobianFactor(fk[k], A0[k], fk[k + 1], A1[k], -steps[k], unit))
        return gfg

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        return self._jacobians(self.offsets(values))

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """The prior as C++ nonlinear factors (exact: the prior is linear in d), for the graph itself
        instead of the solver's block list: LinearContainerFactors of the Jacobians at d = 0.

        The same (dt_k, σ_d, τ_d) gives the same factors, and GTSAM never modifies a factor in a graph, so
        the last graph is reused (every ML round of a session builds this prior again: ≈ 20 ms each)."""
        tag = (self.dt_k.tobytes(), np.asarray(self.sigma_d, float).tobytes(), float(self.tau_d))
        if _LAST_FACTORS.get("tag") != tag:
            _LAST_FACTORS.update(tag=tag, graph=self._linear_container())
        return _LAST_FACTORS["graph"]

    def _linear_container(self) -> gtsam.NonlinearFactorGraph:
        K = self.n_keyframes
        zero = gtsam.Values()
        for key in state_keys(field_key, K):
            zero.insert(key, np.zeros(3))
        return gtsam.LinearContainerFactor.ConvertLinearGraph(self._jacobians(np.zeros((K, 3))), zero)
