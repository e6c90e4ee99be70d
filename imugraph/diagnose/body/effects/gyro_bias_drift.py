"""gyro_bias_drift for body sessions: one sensor's gyro bias drifts beyond the base model's random walk
(1e-3 rad/s/√s over 1 s segments, prior σ 0.002 rad/s around the N-pose rest's mean, imugraph.graphs.body_model).

Model (single-IMU effects/gyro_bias_drift.py, per sensor): ỹ_g,i = s_ω_i + b̂_g(t_i) + β(t_i) + e_g,i with
β(t) = Σ_{p=1..3} c_p P_p(τ) (Legendre in τ ∈ [−1, 1] over the session: `legendre_basis`, imported), 9
parameters. Fit (BE1): the measurement change of c_p,a is −P_p(τ_i) e_a (first order, by a small step).
Relevance: peak-to-peak of β ≥ 0.1 °/s (RELEVANT_DEG_S, imported). Injection: the single-IMU module's `inject`
(0.2–1 °/s, warm-up / linear / wander) on the chosen sensor's Session.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.body.effects.base import BodyCorrection, PerSensorEffect, changed_columns, linear_fit
from imugraph.diagnose.effects.gyro_bias_drift import EFFECT as SINGLE, RELEVANT_DEG_S, legendre_basis


class BodyGyroBiasDrift(PerSensorEffect):
    name = "gyro_bias_drift"
    channel = "gyr"
    single = SINGLE

    def fit(self, bfit, sensor, train, sigma) -> BodyCorrection:
        t = np.asarray(bfit.session.t, float)
        B = legendre_basis(t, float(t[0]), float(t[-1]))
        deltas = []
        for p in range(B.shape[1]):
            for a in range(3):
                d = np.zeros((t.size, 3))
                d[:, a] = -B[:, p]
                deltas.append(d)
        cols = changed_columns(bfit, sensor, deltas, "gyr", key=self.name)
        theta, res = linear_fit(bfit.sensors[sensor].residuals, cols, sigma, train)
        C = theta.reshape(B.shape[1], 3)
        beta = B @ C
        ptp = float(np.rad2deg(np.max(np.ptp(beta, axis=0))))
        return BodyCorrection(self.name, sensor, {"legendre_coefficients_rad_s": C.tolist(), "peak_to_peak_deg_s": ptp},
                              C.size, self.channel, res,
                              size={"value": ptp, "threshold": RELEVANT_DEG_S, "unit": "°/s"},
                              deltas={"gyr": -beta})


EFFECT = BodyGyroBiasDrift()
