"""accelerometer_bias for body sessions: one sensor's accelerometer carries a constant offset beyond what the
base model's bias (prior σ 0.2 m/s² around 0, random walk 2e-3 m/s²/√s, imugraph.graphs.body_model) absorbed.

Model (single-IMU effects/accelerometer_bias.py (A1), per sensor): ỹ_a,i = s_f_i + b̂_a(t_i) + δ_a + e_a,i.
Fit (BE1): the measurement change of δ_a is −δ_a at every sample, exact (3 columns). Relevance: |δ_a| ≥
0.05 m/s² (the single-IMU threshold, RELEVANT_MS2, imported). Injection: the single-IMU module's
`inject` (|δ_a| 0.1–0.5 m/s², random direction) on the chosen sensor's Session.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.body.effects.base import BodyCorrection, PerSensorEffect, changed_columns, linear_fit
from imugraph.diagnose.effects.accelerometer_bias import EFFECT as SINGLE, RELEVANT_MS2


class BodyAccelerometerBias(PerSensorEffect):
    name = "accelerometer_bias"
    channel = "pos"
    single = SINGLE

    def fit(self, bfit, sensor, train, sigma) -> BodyCorrection:
        n = bfit.session.n
        deltas = []
        for a in range(3):
            d = np.zeros((n, 3))
            d[:, a] = -1.0
            deltas.append(d)
        cols = changed_columns(bfit, sensor, deltas, "acc", key=self.name)
        theta, res = linear_fit(bfit.sensors[sensor].residuals, cols, sigma, train)
        size = float(np.linalg.norm(theta))
        return BodyCorrection(self.name, sensor, {"bias_ms2": theta.tolist()}, 3, self.channel, res,
                              size={"value": size, "threshold": RELEVANT_MS2, "unit": "m/s²"},
                              deltas={"acc": np.broadcast_to(-theta, (n, 3)).copy()})


EFFECT = BodyAccelerometerBias()
