"""gyro_scale: scale-factor errors and axis misalignment of the gyroscope.

Model: b_gyr,j = (I + M) ω_j + δ_ω + e_ω, M 3×3 (diagonal: scale-factor errors; off-diagonal: each
sensitive axis tilted toward the others, non-orthogonality and misalignment).                         (S1')

Fit: the keyframes-fixed first-order fit (`_fit_first_order`, effects/base.py rule 1) by default;
with effects/joint.ENABLED (issue 5, G6; the default since G7/H7): M jointly with the trajectory (effects/joint.py (J1)): the keyframe rotations, the
constant gyro bias and the magnetometer's D, o, dip are re-estimated with M on the training samples of
every channel at the base fit's σ (Gauss–Newton, exact residuals), so M is not the fraction of the effect
that the bent base keyframes leave in the gyro residual. The old first-order fit (keyframes fixed) and
the alternation of refit.py grew on clean and injected hosts alike (clean BROAD 06: 0.30 → 1.06 % from
1 to 8 rounds, docs/diagnose.md §4 G2). M is SYMMETRIC (6 parameters: scale factors and
non-orthogonality): its antisymmetric part, a rotation of the gyro's axes against the accelerometer's,
is seen by the accelerometer alone, and on hand-held data it absorbs the linear acceleration (clean
BROAD 06, free: 7 % ≈ 4° about x; the calibration's gyro map holds it with σ 1e-3 for the same reason,
graphs/gyro_map_block.py). Measured (06 crop, harness case 009): clean ‖M‖₂ 1.06 %, with 2.45/2.03/1.10 %
injected the difference of the two fits' diagonals 2.38/1.99/1.08 %; a simulation: exact to 0.03 %.

Relevance (`size`): ‖M‖₂ ≥ 0.3 %.

Injection ranges (RANGES): scale-factor error 0.5–3 % per axis (random sign), each axis misaligned by
0.5–2° toward a random perpendicular direction (MEMS gyros: ±1–3 % scale, ≤ 1–2° non-orthogonality).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects import joint
from imugraph.diagnose.effects.base import (Correction, Effect, check_train, gyro_exact, gyro_refit, huber_weights,
                                             noise_scale, replace_session)
from imugraph.diagnose.effects.trajectory import cached_columns

RANGES = {"scale": (0.005, 0.03), "misalignment_deg": (0.5, 2.0)}
FIT_CHANNELS = ("gyr",)      # the first-order fit's rows
HUBER_K = 2.0
GN_STEPS = 2                 # Gauss–Newton steps of the first-order fit (the residuals are evaluated exactly)
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


def symmetric(p: np.ndarray) -> np.ndarray:
    """M from its 6 free entries (m00, m11, m22, m01, m02, m12): the symmetric part (J1, module doc)."""
    m00, m11, m22, m01, m02, m12 = p
    return np.array([[m00, m01, m02], [m01, m11, m12], [m02, m12, m22]])


class GyroCorrection(Correction):
    """A gyro effect fitted jointly with the trajectory (effects/joint.py): its residuals are those of
    the extended model (moved trajectory) on the fit it was estimated on, else the exact re-integration
    with that fit's keyframes (trajectory.gyro_exact); the corrected data change the gyro only."""

    def raw_residuals(self, fit) -> dict:
        if self.deltas.get("of") is fit and "residuals" in self.deltas:
            return {c: v.copy() for c, v in self.deltas["residuals"].items()}
        return gyro_exact(fit, self.deltas["d_omega"])

    def corrected(self, fit) -> dict:
        """The gyro with the effect removed (y + Δω of the effect alone: the bias, the trajectory and the
        magnetometer calibration re-estimated with it are the refit's to find); acc and mag as recorded."""
        d = self.deltas.get("d_effect", self.deltas["d_omega"])
        return {"gyr": fit.session.gyr + np.nan_to_num(np.asarray(d, float))}


GyroScaleCorrection = GyroCorrection


class FirstOrderCorrection(Correction):
    """The keyframes-fixed correction (before G6): residuals by exact re-integration (gyro_exact)."""

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
        """M (symmetric) jointly with the trajectory, δ_ω and the magnetometer calibration on the training
        samples (effects/joint.py (J1)); Δω = (I+M)⁻¹(y−b) − (y−b) exactly."""
        train = check_train(fit, train)
        if not joint.ENABLED:
            return self._fit_first_order(fit, train)
        w_rate = fit.session.gyr - fit.b_gyr_bias                                  # y − b

        def exact(p):
            return np.linalg.solve(np.eye(3) + symmetric(p), w_rate.T).T - w_rate  # (I+M)⁻¹(y−b) − (y−b)

        out = joint.fit_gyro_effect(fit, train, exact, 6, tag=self.name)
        M = symmetric(out["p"])
        corr = GyroScaleCorrection(self.name, {"M": M.tolist(), "scale_percent": (100 * np.diag(M)).tolist()},
                                   n_params=6, channel=self.channel,
                                   deltas={"d_omega": out["d_omega"], "d_effect": out["d_effect"],
                                           "residuals": out["residuals"], "of": fit, "heldout": out["heldout"]})
        corr.deltas["noise_scale"] = noise_scale(fit, out["residuals"], train, ["gyr", "acc", "mag"])
        return corr

    def _fit_first_order(self, fit, train) -> Correction:
        """The keyframes-fixed fit (before G6; with joint.ENABLED False)."""
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
            sw = np.concatenate([np.repeat(huber_weights(zc, HUBER_K), 3) for zc in z])
            y = np.concatenate([zc.reshape(-1) for zc in z])
            M = M + np.linalg.lstsq(A * sw[:, None], -y * sw, rcond=None)[0].reshape(3, 3)
            d_omega = np.linalg.solve(np.eye(3) + M, w_rate.T).T - w_rate           # (I+M)⁻¹(y−b) − (y−b)
            r = gyro_exact(fit, d_omega)
        corr = FirstOrderCorrection(self.name, {"M": M.tolist(), "scale_percent": (100 * np.diag(M)).tolist()},
                                   n_params=9, channel=self.channel, deltas={"d_omega": d_omega})
        corr.deltas["noise_scale"] = noise_scale(fit, r, train, ["gyr", "acc", "mag"])
        return corr


    def size(self, corr, fit) -> dict:
        """‖M‖₂ (largest scale/misalignment error; relevance ≥ 0.3 %: 1° of heading per turn)."""
        M = np.asarray(corr.params["M"], float)
        return {"value": float(np.linalg.norm(M, 2)), "threshold": RELEVANT_SCALE, "unit": "‖M‖₂"}


EFFECT = GyroScale()
