"""The Gauss–Markov prior of the field perturbation d_k (imugraph.factors.field) as one linear block.

The prior is linear in d, so its JacobianFactors are exact:

    [ I/σ_d ] d_0 = −d_0/σ_d (at the linearisation point),   [ −φ_k I/σ_w,k   I/σ_w,k ] [δd_k; δd_{k+1}]
                                                               = −(d_{k+1} − φ_k d_k)/σ_w,k
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph.factors.field import field_key, field_prior_terms
from imugraph.graphs.solver import keyframe_vectors


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

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        d = self.offsets(values)
        start, steps, phi, sigma_w = field_prior_terms(d, self.dt_k, self.sigma_d, self.tau_d)
        unit = gtsam.noiseModel.Unit.Create(3)
        gfg = gtsam.GaussianFactorGraph()
        sig = np.broadcast_to(np.asarray(self.sigma_d, float), (3,))
        gfg.push_back(gtsam.JacobianFactor(field_key(0), np.diag(1.0 / sig), -start, unit))
        for k in range(len(steps)):
            gfg.push_back(gtsam.JacobianFactor(field_key(k), np.diag(-phi[k] / sigma_w[k]),
                                               field_key(k + 1), np.diag(1.0 / sigma_w[k]), -steps[k], unit))
        return gfg
