"""accelerometer_bias: a constant body-frame offset of the accelerometer.

Model (DESIGN.md (S2) with δ_a): b_acc,j = bRn,j (0, 0, g) + δ_a + e_a.                               (A1)

Fit (training samples only): with the trajectory fixed, the residual is linear in δ_a and in a change δg of
the gravity magnitude (the base fit's g, a median of |acc|, absorbs the bias' component along gravity):
acc_j ≈ δ_a + δg R̂_jᵀ ẑ — 4-parameter least squares. Correction: acc'_j = acc_j − δ_a − δg R̂_jᵀ ẑ.

Relevance (`size`): |δ_a| ≥ 0.05 m/s².

Injection ranges (RANGES): |δ_a| = 0.1–0.5 m/s² in a random direction (uncalibrated MEMS accelerometers:
tens of mg after soldering and with temperature).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import Correction, Effect, check_train, noise_scale, replace_session

RANGES = {"bias_ms2": (0.1, 0.5)}
RELEVANT_MS2 = 0.05          # relevance: |δ_a| ≥ 0.05 m/s² (5 mg, ≥ 0.3° of tilt)


class AccBiasCorrection(Correction):
    def raw_residuals(self, fit) -> dict:
        out = {c: fit.residuals[c].copy() for c in fit.residuals}
        z_b = fit.nRb[:, 2, :]                                                      # R̂ᵀ ẑ (rows of R̂)
        out["acc"] = out["acc"] - np.asarray(self.params["bias_ms2"]) - self.params["gravity_change"] * z_b
        return out


class AccelerometerBias(Effect):
    name = "accelerometer_bias"
    channel = "acc"
    windowed = False
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """Add δ_a. strength: |δ_a| in m/s² (default random in RANGES)."""
        mag = float(strength) if strength is not None else float(rng.uniform(*RANGES["bias_ms2"]))
        d = rng.standard_normal(3)
        bias = mag * d / np.linalg.norm(d)
        truth = {"params": {"bias_ms2": bias.tolist(), "norm_ms2": mag}, "t_start": None, "t_end": None}
        return replace_session(session, acc=session.acc + bias, name_suffix="+accelerometer_bias",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        train = check_train(fit, train)
        r = fit.residuals["acc"]
        ok = train & np.all(np.isfinite(r), axis=1)
        z_b = fit.nRb[:, 2, :]
        J = np.zeros((fit.n, 3, 4))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3] = z_b
        w = 1.0 / np.asarray(fit.sigma["acc"], float)
        A = (J[ok] * w[None, :, None]).reshape(-1, 4)
        theta = np.linalg.lstsq(A, (r[ok] * w).reshape(-1), rcond=None)[0]
        corr = AccBiasCorrection(self.name, {"bias_ms2": theta[:3].tolist(), "gravity_change": float(theta[3])},
                                 n_params=4, channel=self.channel)
        corr.deltas["noise_scale"] = noise_scale(fit, corr.raw_residuals(fit), train, ["acc"])
        return corr


    def size(self, corr, fit) -> dict:
        """|δ_a|, m/s² (relevance ≥ 0.05 m/s² ≈ 5 mg: a tilt error ≥ 0.3°)."""
        return {"value": float(np.linalg.norm(corr.params["bias_ms2"])), "threshold": RELEVANT_MS2,
                "unit": "m/s²"}


EFFECT = AccelerometerBias()
