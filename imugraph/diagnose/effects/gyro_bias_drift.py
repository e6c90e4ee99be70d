"""gyro_bias_drift: the gyroscope bias drifts over the session (warm-up, temperature).

Model: b_gyr,j = ω_j + δ_ω + β(t_j) + e_ω with a smooth drift β(t), by `BASIS`:
  "legendre" (default): β(t) = Σ_p c_p P_p(τ_j), P_p the Legendre polynomials of degree 1…3 in
      τ = 2(t − t₀)/(t₁ − t₀) − 1 (9 parameters; the constant is the base bias)                         (D1)
  "spline" (issue 5, S14-B; `DiagnoseOptions.drift_basis`): piecewise linear with knots every ≈ KNOT_S = 10 s,
      β(t₀) = 0 (`hat_basis` (D2); 3 parameters per knot: 18 on a 60 s crop, 54 on a 3-minute trial).
      It nests the ramp and holds a slow "wander" the cubic cannot (docs/diagnose.md §4 S14-B: BROAD 04 +
      the harness' wander ×10 (3 °/s): (J6) S 0.685 against 0.013 with the cubic).

Fit: the keyframes-fixed first-order fit (`_fit_first_order`, effects/base.py rule 1) by default;
with effects/joint.ENABLED (issue 5, G6; the default since G7/H7): the coefficients c_p jointly with the trajectory (effects/joint.py (J1): keyframe
rotations, constant bias and magnetometer calibration re-estimated with them on the training samples of
every channel, the base fit's σ); the extended model's bias is b̄ + β(t), so the gyro changes by
Δω_j = b_s(j) − b̄ − β(t_j). β is smooth and global, so the held-out blocks are interpolated. (Before: the
keyframes held fixed, and the alternation of refit.py grew the drift on clean hosts as on injected ones:
clean BROAD 04 0.54 → 1.20 °/s from 1 to 8 rounds, docs/diagnose.md §4 G2.)

The base model has ONE constant bias (imugraph.diagnose.fit), so a drift is left to this effect.
Relevance (`size`): peak-to-peak of β ≥ 0.1 °/s.

Injection ranges (RANGES): total change |β(t₁) − β(t₀)| or peak-to-peak 0.2–1 °/s over the session in a
random direction; shape "warm-up" (1 − e^{−(t−t₀)/τ}, τ = 0.2–1 × duration), "linear" ramp, or "wander"
(two slow sinusoids, periods 0.5–2 × duration).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects import joint
from imugraph.diagnose.effects.base import (Correction, Effect, check_train, gyro_refit, noise_scale,
                                             replace_session)
from imugraph.diagnose.effects.gyro_scale import FirstOrderCorrection, GyroCorrection
from imugraph.diagnose.effects.trajectory import cached_columns

RANGES = {"drift_deg_s": (0.2, 1.0), "shapes": ("warm-up", "linear", "wander")}
RELEVANT_DEG_S = 0.1         # relevance: a drift of ≥ 0.1 °/s integrates to ≥ 6° of heading per minute
DEGREE = 3


def legendre_basis(t: np.ndarray, t0: float, t1: float, degree: int = DEGREE) -> np.ndarray:
    """(N, degree) Legendre polynomials P_1…P_degree of τ ∈ [−1, 1]."""
    tau = 2.0 * (t - t0) / max(t1 - t0, 1e-9) - 1.0
    return np.stack([np.polynomial.legendre.Legendre.basis(p)(tau) for p in range(1, degree + 1)], axis=1)


# The drift's basis (DiagnoseOptions.drift_basis sets it per diagnosis): "legendre" (the cubic above, default)
# or "spline" (`hat_basis`: piecewise linear, knots every ≈ KNOT_S s, docs/diagnose.md §4 S14-B).
BASIS = "legendre"
KNOT_S = 10.0


def hat_basis(t: np.ndarray, t0: float, t1: float, knot_s: float = KNOT_S) -> np.ndarray:
    """(N, K) linear B-splines ("hat" functions) at the K knots t0 + kΔ, k = 1…K, Δ = (t1 − t0)/K with
    K = ⌈(t1 − t0)/knot_s⌉:

        β(t) = Σ_k c_k h_k(t),  h_k(t) = max(0, 1 − |x(t) − k|),  x(t) = K (t − t0)/(t1 − t0)       (D2)

    piecewise linear between the knots, β(t0) = 0 (the knot at t0 is left out: a constant is the base
    model's bias). It represents every drift slower than the knot spacing — a ramp exactly, a warm-up or a
    wander of period ≥ ~3Δ closely — where the cubic (D1) holds a ramp and a warm-up but not a wander
    (28 % of harness case 006's variance, docs/diagnose.md §4 G7)."""
    K = max(1, int(np.ceil((t1 - t0) / max(knot_s, 1e-9) - 1e-9)))
    x = np.clip((t - t0) / max(t1 - t0, 1e-9) * K, 0.0, K)
    return np.stack([np.clip(1.0 - np.abs(x - k), 0.0, None) for k in range(1, K + 1)], axis=1)


def drift_basis(t: np.ndarray) -> np.ndarray:
    """The drift's basis (N, P/3) over the session t, by `BASIS`: (D1) or (D2)."""
    t0, t1 = float(t[0]), float(t[-1])
    return hat_basis(t, t0, t1, KNOT_S) if BASIS == "spline" else legendre_basis(t, t0, t1)


def drift_params(C: np.ndarray, beta: np.ndarray) -> dict:
    """Correction.params of a fitted drift: its basis' coefficients (P/3, 3) and β's peak-to-peak."""
    out = {"legendre_coefficients_rad_s": C.tolist()} if BASIS != "spline" else \
        {"basis": "spline", "knot_s": KNOT_S, "spline_coefficients_rad_s": C.tolist()}
    out["peak_to_peak_deg_s"] = float(np.rad2deg(np.max(np.ptp(beta, axis=0))))
    return out


DriftCorrection = GyroCorrection


class GyroBiasDrift(Effect):
    name = "gyro_bias_drift"
    channel = "gyr"
    windowed = False
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """Add β(t). strength: drift magnitude in °/s (default random in RANGES)."""
        mag = np.deg2rad(float(strength) if strength is not None else rng.uniform(*RANGES["drift_deg_s"]))
        t = session.t
        T = float(t[-1] - t[0])
        x = (t - t[0]) / max(T, 1e-9)
        shape = str(rng.choice(RANGES["shapes"]))
        if shape == "warm-up":
            s = 1.0 - np.exp(-x / rng.uniform(0.2, 1.0))
        elif shape == "linear":
            s = x
        else:
            p1, p2 = rng.uniform(0.5, 2.0, 2)
            s = np.sin(2 * np.pi * x / p1 + rng.uniform(0, 2 * np.pi)) + 0.5 * np.sin(2 * np.pi * x / p2)
        s = s - s[0]
        s = s / max(float(np.ptp(s)), 1e-12)
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        beta = mag * s[:, None] * d
        truth = {"params": {"drift_rad_s": float(mag), "drift_deg_s": float(np.rad2deg(mag)), "shape": shape,
                            "direction": d.tolist()}, "t_start": None, "t_end": None}
        return replace_session(session, gyr=session.gyr + beta, name_suffix="+gyro_bias_drift",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        """β's coefficients jointly with the trajectory, δ_ω and the magnetometer calibration on the
        training samples (effects/joint.py (J1)); Δω = b_s(j) − b̄ − β(t_j) (linear in the coefficients)."""
        train = check_train(fit, train)
        if not joint.ENABLED:
            return self._fit_first_order(fit, train)
        t = fit.session.t
        B = drift_basis(t)
        seg = fit.b_gyr_bias - np.asarray(fit.calibration.gyro_bias, float)         # b_s(j) − b̄

        def exact(p):
            return seg - B @ np.asarray(p, float).reshape(B.shape[1], 3)            # Δω = b_s − b̄ − β

        out = joint.fit_gyro_effect(fit, train, exact, B.shape[1] * 3, tag=f"{self.name}:{BASIS}")
        C = out["p"].reshape(B.shape[1], 3)
        beta = B @ C
        corr = DriftCorrection(self.name, drift_params(C, beta),
                               n_params=C.size, channel=self.channel,
                               deltas={"d_omega": out["d_omega"], "d_effect": out["d_effect"],
                                           "residuals": out["residuals"], "of": fit, "heldout": out["heldout"]})
        corr.deltas["noise_scale"] = noise_scale(fit, out["residuals"], train, ["gyr", "acc", "mag"])
        return corr

    def _fit_first_order(self, fit, train) -> Correction:
        """The keyframes-fixed fit (before G6; with joint.ENABLED False)."""
        t = fit.session.t
        B = drift_basis(t)
        seg = fit.b_gyr_bias - np.asarray(fit.calibration.gyro_bias, float)         # b_s(j) − b̄
        base = fit.residuals

        def columns():
            r0, _ = gyro_refit(fit, seg)                                             # β = 0
            out = []
            for p in range(B.shape[1]):
                for a in range(3):
                    d = np.zeros((fit.n, 3))
                    d[:, a] = -B[:, p]
                    r1, _ = gyro_refit(fit, seg + d)
                    out.append({c: r1[c] - r0[c] for c in base})
            return r0, out

        r0, cols = cached_columns(fit, f"{self.name}:{BASIS}", columns)             # shared by the folds
        rows_A, rows_y = [], []
        for c in ("gyr", "acc", "mag"):
            ok = train & np.all(np.isfinite(r0[c]), axis=1)
            s = np.asarray(fit.sigma[c], float)
            rows_A.append(np.stack([(col[c][ok] / s).reshape(-1) for col in cols], axis=1))
            rows_y.append((r0[c][ok] / s).reshape(-1))
        coef = np.linalg.lstsq(np.concatenate(rows_A), -np.concatenate(rows_y), rcond=None)[0]
        C = coef.reshape(B.shape[1], 3)
        beta = B @ C
        d_omega = seg - beta
        corr = FirstOrderCorrection(self.name, drift_params(C, beta),
                               n_params=C.size, channel=self.channel, deltas={"d_omega": d_omega})
        res = corr.raw_residuals(fit)
        corr.deltas["noise_scale"] = noise_scale(fit, res, train, ["gyr", "acc", "mag"])
        return corr


    def size(self, corr, fit) -> dict:
        """Peak-to-peak of β(t) over the session, largest axis, °/s (relevance ≥ 0.1 °/s: 6° per minute)."""
        return {"value": float(corr.params["peak_to_peak_deg_s"]), "threshold": RELEVANT_DEG_S, "unit": "°/s"}


EFFECT = GyroBiasDrift()
