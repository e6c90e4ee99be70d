"""Full refit of the base model extended with one effect (the attribution's second stage).

A residual-level correction (an effect's `fit` on the base fit, trajectory fixed) recovers only part of
an effect that bent the base fit: a magnet pulls the fitted D, o, σ_mag and heading toward it, a gyro
scale error turns the fitted trajectory, an accelerometer bias tilts it. The extended model is refitted
by alternation (block coordinate descent on the joint ML problem):

    round r = 1, 2:   φ_r  = E.fit(θ_{r−1} on y, all samples)            (effect from scratch, original y)
                      y_r  = E⁻¹(y; φ_r)                                  (Correction.corrected: effect removed)
                      F_r  = fit_base(y_r), started from F_{r−1}: θ_r     (trajectory, D, o, dip, bias, σ)   (F1)

stopped early (θ* = θ_{r−1}) when ‖y_r − y_{r−1}‖ < CONVERGED · ‖y_r − y‖ on every corrected channel:
the refit would start from θ_{r−1} on (nearly) the same data. With effects/joint.ENABLED (opt-in, G6) the
gyro effects (gyro_scale, gyro_bias_drift) estimate φ_r jointly with the trajectory, so their φ_1 is the
joint estimate and round 2 confirms it (clean BROAD 06 crop: ‖M‖₂ 1.057, 1.071, 1.072 % over rounds 1–3;
with the keyframes held fixed it grew 0.30 → 1.06 % over 8 rounds, docs/diagnose.md §4 G2/G6).

Where imugraph.calibration.ml has the effect as a joint model (`Effect.joint_options`, e.g.
magnetic_disturbance ↔ windowed hard-iron offsets, `disturbance_windows=True`), θ* is that joint fit
instead of the alternation. F_0 = the base fit of the recording. The extended model's base parameters θ* are those of F_2. The
cross-validation then evaluates the effect from scratch on the ORIGINAL measurements against θ*
(`on_session`): per fold, φ_k = E.fit(θ*, training blocks), residuals y − h(θ*, φ_k) on the held-out
blocks. θ* is fitted on all samples, as the base model's θ is for the "before" residuals; only the
effect's parameters are cross-validated. (θ* saw the held-out samples through the correction of (F1),
whose parameters φ_r are few and global or per window: a weak leak, stated in docs/diagnose.md.)

Which refits are needed (speed, issue 5): by the verdict rule (V) of imugraph.diagnose.attribute a
significant, relevant, localised effect is the verdict ahead of every global one. The candidates that may
be localised are refitted first (`refit_order`); once one of them is the verdict (`verdict_is_local`), the
refits of effects that cannot be localised (`may_be_localised`) cannot change it and are skipped — an
exact bound, not a threshold (BROAD 32, magnet: the 5 global refits of its 6 candidates).

Opt-in (S20-Mb, docs/diagnose.md §S20-Mb): ACCELERATE (F2) — the alternation converges linearly (a window's
field and the heading and bias inside it are coupled blocks); 4 rounds and an Aitken jump reach its fixed point
(`_aitken`). HOLD_NOISE — the rounds keep the base fit's noise levels (measured: worse, not recommended).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from imugraph.diagnose.effects.base import base_rms, huber_rms, replace_session
from imugraph.diagnose.effects.trajectory import reintegrate
from imugraph.diagnose.fit import Fit, _raw_residuals, body_rate, fit_simulation


def on_session(fit: Fit, session) -> Fit:
    """The fitted parameters and keyframes of `fit` with residuals (R1)–(R3) of another session on the
    same time base (the original measurements of a fit of corrected ones).

    When the gyro differs (a gyro effect was removed before the refit), the per-sample orientations
    between the keyframes are integrated again from `session`'s gyro (forward from R̂_k, backward from
    R̂_{k+1}, slerp-blended, as the fit does): the fit's own sample orientations follow the CORRECTED gyro,
    so the original gyro's residual (R1) would hold the whole per-sample correction −Δω_j, which the
    effect's first-order refit (base (E2): only the interval mean Φ_k/T_k) cannot remove. With the
    keyframes fixed and the samples integrated from the original gyro, (R1) is again the keyframe
    mismatch rate c_k of the module doc of imugraph.diagnose.fit, and (E1)–(E3) apply around θ*."""
    out = replace(fit, session=session, residuals={})
    if not np.array_equal(session.gyr, fit.session.gyr, equal_nan=True):
        out.nRb = reintegrate(fit, session.gyr)
        out.b_omega = body_rate(out.nRb, session.dt)
    out.residuals = _raw_residuals(out)
    return out


def refit_effect(effect, real: Fit, rounds: int = 2, window=None) -> tuple[Fit, dict]:
    """Alternation (F1) for one effect. Returns (θ* on the original measurements, info) where info holds
    the rounds' parameters, the window handed on between rounds and "changed" (False when the effect
    corrected nothing, e.g. no rail found: θ* is then the base fit)."""
    joint = getattr(effect, "joint_options", None)
    if joint:                                   # the calibration has the extended model: fit it jointly
        from imugraph.diagnose.fit import base_options, fit_base

        ext = fit_base(real.session, base_options(real.info.get("keyframe_hz", 5.0)), extended=dict(joint),
                       align_mag=False)       # real.session's field is already on the gyro's time base (B3)
        ext.info["mag_delay_s"] = real.info.get("mag_delay_s", 0.0)
        ext.info["mag_subsample_s"] = real.info.get("mag_subsample_s", 0.0)
        return ext, {"rounds": [], "window": window, "changed": True, "joint": dict(joint)}
    cur = real
    info = {"rounds": []}
    train = np.ones(real.n, bool)
    seq = []                                   # the corrected data of every round (seq[-1]: the previous one)
    stop = CONVERGED / 10.0 if ACCELERATE else CONVERGED
    opts = refit_options(real)                 # S20-Mb: σ held?
    for _ in range(max(rounds, ACCEL_ROUNDS) if ACCELERATE else rounds):
        view = real if cur is real else on_session(cur, real.session)
        corr = effect.fit(view, train, window=window)
        new = corr.corrected(view) if hasattr(corr, "corrected") else {}
        info["rounds"].append({"params": corr.params, "t_start": corr.t_start, "t_end": corr.t_end})
        if not new:
            break
        if seq and _change(new, seq[-1], real.session) < stop:
            info["converged"] = True          # y_r ≈ y_{r−1}: fit_base would return θ_{r−1} again
            break
        cur = fit_simulation(replace_session(real.session, **new), cur, opts)
        cur.info["mag_delay_s"] = real.info.get("mag_delay_s", 0.0)   # θ_r's data: the recording's τ_m (B3)
        seq.append(new)
    if ACCELERATE and len(seq) >= 3 and not info.get("converged"):                          # (F2)
        jump, rho = _aitken(seq[-3:])
        info["rho"] = rho
        if jump is not None:
            cur = fit_simulation(replace_session(real.session, **jump), cur, opts)
            cur.info["mag_delay_s"] = real.info.get("mag_delay_s", 0.0)
            info["extrapolated"] = True
    info["window"] = window
    info["changed"] = cur is not real
    return on_session(cur, real.session), info


CONVERGED = 0.02     # relative change of the corrected data below which the alternation stops
# S20-Mb (F2), opt-in (DiagnoseOptions.refit_accelerate): the alternation's fixed point by extrapolation. The
# field of a window and the heading/bias inside it are coupled blocks, so (F1) converges linearly and slowly:
# on a simulated 0.5 |m| attached magnet (tests/test_diagnose_refit_gyro.py) the gyro whitened RMS of θ_r is
# 5.95, 4.58 (r = 2, the default; the 2 % stop ends it at r = 3), 2.74 (r = 4), 1.50 (r = 8), 1.31 (r = 16,
# = the refit of the clean data): ρ ≈ 0.75 per round. (F2) runs ACCEL_ROUNDS rounds (stop at CONVERGED/10),
# then one fit on the Aitken extrapolation of the corrected data,  y_∞ ≈ y_r + Δ_r ρ/(1 − ρ),  Δ_r = y_r − y_{r−1},
# ρ = ‖Δ_r‖ / ‖Δ_{r−1}‖ (ρ ≥ RHO_MAX: no jump, θ* = θ_r). Same simulation: 3 rounds + jump (ρ 0.49, the
# first round's move not yet geometric) 2.51; 4 rounds + jump (ρ 0.71) 1.34; 5 + jump 1.31.
ACCELERATE = False
ACCEL_ROUNDS = 4
RHO_MAX = 0.95
HOLD_NOISE = False   # S20-Mb: the refits' noise levels held at the base fit's (DiagnoseOptions.refit_hold_noise; opt-in)


def refit_options(real: Fit):
    """The calibration Options of a refit θ_r (F1): the base model's, with the noise levels held at the base
    fit's when HOLD_NOISE (S20-Mb); None: fit_simulation's default (the noise re-estimated)."""
    if not HOLD_NOISE:
        return None
    from imugraph.diagnose.fit import base_options

    return replace(base_options(real.info.get("keyframe_hz", 5.0)), reestimate_noise=False)


def may_be_localised(effect, screened) -> bool:
    """Whether the refit of `effect` could make it a localised effect (support < half the recording,
    attribute (A3)/(V)): a windowed effect (its windows come from the fit), one whose screening claimed a
    support (saturation's rails) or whose evidence is conclusive. The others (linear_acceleration,
    gyro_scale, gyro_bias_drift, time_offset, accelerometer_bias) claim the whole recording whatever θ*."""
    return bool(getattr(effect, "windowed", False) or getattr(screened, "decisive", False)
                or getattr(screened, "support_fraction", 1.0) < 1.0)


def refit_order(names: list, screened: dict, effects: dict) -> list:
    """The candidates with those that may be localised first (stable otherwise): a localised verdict
    found early lets `verdict_is_local` skip the refits that cannot change it."""
    return sorted(names, key=lambda n: not may_be_localised(effects[n], screened[n]))


def verdict_is_local(refitted: list, null_gap: dict, opt) -> bool:
    """True when a refitted effect is localised, significant and relevant. By the verdict rule (V) the
    verdict is then a localised effect whatever the refits of effects that cannot be localised
    (`may_be_localised` False) give: they can only re-rank the global effects, which (V) puts after
    every localised one. An exact bound (no threshold of its own): skipping those refits leaves the
    verdict unchanged; their entries in `effects[]` keep the screening stage."""
    from imugraph.diagnose.attribute import LOCAL_FRACTION, significant

    return any(r.stage == "refit" and r.support_fraction < LOCAL_FRACTION and r.relevant
               and significant(r, null_gap, opt) for r in refitted)


def _aitken(seq: list) -> tuple:
    """(F2): (y_r + Δ_r ρ/(1 − ρ) per corrected channel, ρ) from the last three rounds' corrected data
    (ρ = ‖Δ_r‖/‖Δ_{r−1}‖ over all corrected channels; NaN rows stay NaN, a row NaN in y_{r−1} does not move);
    (None, ρ) when the channels differ between rounds or ρ is not in (0, RHO_MAX)."""
    a, b, c = seq
    if not (set(a) == set(b) == set(c)):
        return None, float("nan")
    d1 = np.sqrt(sum(np.sum(np.nan_to_num(b[k] - a[k]) ** 2) for k in c))
    d2 = np.sqrt(sum(np.sum(np.nan_to_num(c[k] - b[k]) ** 2) for k in c))
    rho = float(d2 / d1) if d1 > 0 else float("nan")
    if not (0.0 < rho < RHO_MAX):
        return None, rho
    return {k: c[k] + np.nan_to_num(c[k] - b[k]) * (rho / (1.0 - rho)) for k in c}, rho


def _change(new: dict, prev: dict, session) -> float:
    """Largest over channels of ‖y_r − y_{r−1}‖ / ‖y_r − y‖: how much the correction changed between two
    rounds, relative to the correction itself (BROAD 01: linear_acceleration 0.004, vibration 0.001 —
    converged after one round; gyro_scale 0.38, accelerometer_bias 0.33 — not)."""
    worst = 0.0 if set(new) == set(prev) else np.inf
    for c in new.keys() & prev.keys():
        step = np.linalg.norm(np.nan_to_num(new[c] - prev[c]))
        size = np.linalg.norm(np.nan_to_num(new[c] - getattr(session, c)))
        worst = max(worst, step / size if size > 0 else (0.0 if step == 0 else np.inf))
    return worst


def rescale(after: dict, real: Fit, train: np.ndarray) -> dict:
    """Noise re-estimation of the extended model (effects/base.py rule 3) for refit residuals: acc and
    mag are scaled by σ_c / σ'_c, σ_c the Huber RMS of the base residuals and σ'_c that of the
    extended model's, both on the training samples, so that whitening by the base σ (what the gap does)
    gives the extended model's standardised residuals."""
    out = {"gyr": after["gyr"]}                 # the gyro σ is measured at rest, never re-estimated
    for c in ("acc", "mag"):
        s0 = base_rms(real, c, train)
        s1 = huber_rms(after[c][train], real.sigma[c])
        out[c] = after[c] * (s0 / s1)
    return out
