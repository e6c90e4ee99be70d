"""gyro_scale: scale-factor errors and axis misalignment of the gyroscope.

Model: b_gyr,j = (I + M) ω_j + δ_ω + e_ω, M 3×3 (diagonal: scale-factor errors; off-diagonal: each
sensitive axis tilted toward the others, non-orthogonality and misalignment).                         (S1')

Fit (first order, base rule 1): removing the effect changes the rate by Δω_j = (I+M)⁻¹(y_j − b_j) −
(y_j − b_j) ≈ −M (y_j − b_j), and the residuals of every channel move linearly with Δω (base (E1)–(E3)).
So each entry m_ab of M has a residual direction G_ab = refit(−E_ab (y − b)) − r (the Jacobian), and M
minimises Σ_train ρ(‖r_gyr(M) / σ‖) over the gyro channel (9 parameters; adding the acc and mag rows changed M
by < 0.1 % on BROAD 01 + injected scale: the gyro rows dominate): GN_STEPS Gauss–Newton
steps, r(M) evaluated exactly (trajectory.gyro_exact, keyframes fixed), Huber weights ρ (k = 2). The
correction uses the exact inverse (I+M)⁻¹.

Relevance (`size`): ‖M‖₂ ≥ 0.3 %.

Injection ranges (RANGES): scale-factor error 0.5–3 % per axis (random sign), each axis misaligned by
0.5–2° toward a random perpendicular direction (MEMS gyros: ±1–3 % scale, ≤ 1–2° non-orthogonality).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, gyro_exact, gyro_refit,
                                             noise_scale, replace_session)
from imugraph.diagnose.effects.trajectory import cached_columns

RANGES = {"scale": (0.005, 0.03), "misalignment_deg": (0.5, 2.0)}
FIT_CHANNELS = ("gyr",)
HUBER_K = 2.0
GN_STEPS = 2                 # Gauss–Newton steps of the fit (the residuals are evaluated exactly)
RELEVANT_SCALE = 0.003       # relevance: ‖M‖₂ ≥ 0.3 % (≈ 1° orientation error per full turn)


def random_scale_matrix(rng: np.random.Generator) -> np.ndarray:
    """I + M: rows (1 + s_i)·u_i, u_i the unit axis e_i tilted by α_i toward a random perpendicular."""
    S = np.zeros((3, 3))
    for i in range(3):
        s = rng.uniform(*RANGES["scale"]) * rng.choice([-1.0, 1.0])
        alpha = np.deg2rad(rng.uniform(*RANGES["misalignment_deg"]))
        e = np.eye(3)[i]
        p = rng.standard_normal(3)
        p -= p @ e * e
        p /= np.linalg.norm(p)
        S[i] = (1.0 + s) * (np.cos(alpha) * e + np.sin(alpha) * p)
    return S


class GyroScaleCorrection(Correction):
    def raw_residuals(self, fit) -> dict:
        return gyro_exact(fit, self.deltas["d_omega"])


class GyroScale(Effect):
    name = "gyro_scale"
    channel = "gyr"
    windowed = False
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """y ← (I + M) y. strength: a given (3, 3) I + M (default random in RANGES)."""
        S = np.asarray(strength, float) if strength is not None else random_scale_matrix(rng)
        gyr = session.gyr @ S.T                                                     # (S1')
        truth = {"params": {"scale_matrix": S.tolist(), "M": (S - np.eye(3)).tolist()},
                 "t_start": None, "t_end": None}
        return replace_session(session, gyr=gyr, name_suffix="+gyro_scale",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        train = check_train(fit, train)
        w_rate = fit.session.gyr - fit.b_gyr_bias                                  # y − b
        base = fit.residuals

        def columns():
            out = []
            for a in range(3):
                for b in range(3):
                    d = np.zeros_like(w_rate)
                    d[:, a] = -w_rate[:, b]                                         # −E_ab (y − b)
                    r1, _ = gyro_refit(fit, d)
                    out.append({c: r1[c] - base[c] for c in base})
            return out

        cols = cached_columns(fit, self.name, columns)                              # shared by the folds
        ok = {c: train & np.all(np.isfinite(base[c]), axis=1) for c in base}
        for c in base:
            for col in cols:
                ok[c] &= np.all(np.isfinite(col[c]), axis=1)
        sg = {c: np.asarray(fit.sigma[c], float) for c in base}
        A = np.concatenate([np.stack([(col[c][ok[c]] / sg[c]).reshape(-1) for col in cols], axis=1)
                            for c in FIT_CHANNELS])
        M = np.zeros((3, 3))
        r = base
        for _ in range(GN_STEPS):             # Gauss–Newton: linear columns, residuals exact (gyro_exact)
            z = [r[c][ok[c]] / sg[c] for c in FIT_CHANNELS]
            # Huber weights per sample (k = HUBER_K on |z|/√3, the calibration's kernel): keyframe intervals
            # pulled by what no gyro parameter explains (hand-held linear acceleration) count less
            sw = np.concatenate([np.repeat(np.sqrt(np.minimum(1.0, HUBER_K / np.maximum(
                np.linalg.norm(zc, axis=1) / np.sqrt(3), 1e-12))), 3) for zc in z])
            y = np.concatenate([zc.reshape(-1) for zc in z])
            M = M + np.linalg.lstsq(A * sw[:, None], -y * sw, rcond=None)[0].reshape(3, 3)
            d_omega = np.linalg.solve(np.eye(3) + M, w_rate.T).T - w_rate           # (I+M)⁻¹(y−b) − (y−b)
            r = gyro_exact(fit, d_omega)
        corr = GyroScaleCorrection(self.name, {"M": M.tolist(), "scale_percent": (100 * np.diag(M)).tolist()},
                                   n_params=9, channel=self.channel, deltas={"d_omega": d_omega})
        corr.deltas["noise_scale"] = noise_scale(fit, r, train, ["gyr", "acc", "mag"])
        return corr


    def size(self, corr, fit) -> dict:
        """‖M‖₂ (largest scale/misalignment error; relevance ≥ 0.3 %: 1° of heading per turn)."""
        M = np.asarray(corr.params["M"], float)
        return {"value": float(np.linalg.norm(M, 2)), "threshold": RELEVANT_SCALE, "unit": "‖M‖₂"}


EFFECT = GyroScale()
