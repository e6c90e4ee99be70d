"""gyro_scale: scale-factor errors and axis misalignment of the gyroscope.

Model: b_gyr,j = (I + M) ω_j + δ_ω + e_ω, M 3×3 (diagonal: scale-factor errors; off-diagonal: each
sensitive axis tilted toward the others, non-orthogonality and misalignment).                         (S1')

Fit (first order, base rule 1): removing the effect changes the rate by Δω_j = (I+M)⁻¹(y_j − b_j) −
(y_j − b_j) ≈ −M (y_j − b_j), and the residuals of every channel move linearly with Δω (base (E1)–(E3)).
So each entry m_ab of M has a residual direction G_ab = refit(−E_ab (y − b)) − r, and M solves the linear
least squares Σ_train ‖(r + Σ m_ab G_ab) / σ‖² over all three channels (9 parameters). The correction then
uses the exact inverse (I+M)⁻¹.

Relevance (`size`): ‖M‖₂ ≥ 0.3 %.

Injection ranges (RANGES): scale-factor error 0.5–3 % per axis (random sign), each axis misaligned by
0.5–2° toward a random perpendicular direction (MEMS gyros: ±1–3 % scale, ≤ 1–2° non-orthogonality).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, gyro_refit, noise_scale,
                                             replace_session)

RANGES = {"scale": (0.005, 0.03), "misalignment_deg": (0.5, 2.0)}
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
        return gyro_refit(fit, self.deltas["d_omega"])[0]


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
        cols = []
        for a in range(3):
            for b in range(3):
                d = np.zeros_like(w_rate)
                d[:, a] = -w_rate[:, b]                                             # −E_ab (y − b)
                r1, _ = gyro_refit(fit, d)
                cols.append({c: r1[c] - base[c] for c in base})
        rows_A, rows_y = [], []
        for c in ("gyr", "acc", "mag"):
            ok = train & np.all(np.isfinite(base[c]), axis=1)
            for col in cols:
                ok &= np.all(np.isfinite(col[c]), axis=1)
            s = np.asarray(fit.sigma[c], float)
            rows_A.append(np.stack([(col[c][ok] / s).reshape(-1) for col in cols], axis=1))
            rows_y.append((base[c][ok] / s).reshape(-1))
        A = np.concatenate(rows_A)
        y = np.concatenate(rows_y)
        m = np.linalg.lstsq(A, -y, rcond=None)[0]
        M = m.reshape(3, 3)
        d_omega = np.linalg.solve(np.eye(3) + M, w_rate.T).T - w_rate               # (I+M)⁻¹(y−b) − (y−b)
        corr = GyroScaleCorrection(self.name, {"M": M.tolist(), "scale_percent": (100 * np.diag(M)).tolist()},
                                   n_params=9, channel=self.channel, deltas={"d_omega": d_omega})
        res = corr.raw_residuals(fit)
        corr.deltas["noise_scale"] = noise_scale(fit, res, train, ["gyr", "acc", "mag"])
        return corr


    def size(self, corr, fit) -> dict:
        """‖M‖₂ (largest scale/misalignment error; relevance ≥ 0.3 %: 1° of heading per turn)."""
        M = np.asarray(corr.params["M"], float)
        return {"value": float(np.linalg.norm(M, 2)), "threshold": RELEVANT_SCALE, "unit": "‖M‖₂"}


EFFECT = GyroScale()
