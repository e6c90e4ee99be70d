"""time_offset: one sensor channel is time-shifted against the others (a sampling or filter delay).

Model: the channel c ∈ {mag, acc, gyr} sampled at t_j reports the value sensed at t_j − τ:

    y_c(t_j) = h_c(x(t_j − τ)) + e_c ≈ h_c(x(t_j)) − τ ḣ_c(t_j) + e_c                              (T1)

Fit (training samples only): for mag and acc, τ by Gauss–Newton on (T1) with ḣ_c the time derivative of
the fitted prediction (two steps, the second at the exactly shifted signal); for gyr, removing the delay
changes the rate by Δω = y(t + τ) − y(t) ≈ τ ẏ and every channel's residuals move linearly with τ (base
(E1)–(E3)). Second candidate per channel, from the raw measurements and the gyro only (independent of
the fitted trajectory, which a delayed channel bends):

    ẏ_c(t) = (y_c × (y_g − b̂))(t − τ_c)   (a constant nav vector — gravity, field — seen from the turning
                                           body), τ_c by `calibration.alignment.estimate_mag_delay`      (T2)

for acc and mag (the field with the fitted hard iron removed); gyr: −τ_acc; every lag of the search
grid solved at once by its 9×9 normal equations (T3, in `estimate_mag_delay`), windows across a held-out block
dropped. The candidate (channel, τ) whose shift lowers the whitened training cost most wins (1 parameter
+ the choice; the channels' costs are summed relative to the base fit's, each channel counting alike).
The gyro candidates (whose exact evaluation re-integrates the trajectory) are skipped when the
first-order floor of their cost (T4, `_first_order_floor`) is above the best acc/mag candidate. The
correction undoes the shift by interpolation: y'_c(t) = y_c(t + τ).

Relevance (`size`): |τ| ≥ one sample period (S20-V (T12), opt-in: + 1.645 × the folds' jackknife SE).

S14-A rules (opt-in: `DiagnoseOptions.timing_rules`, module flags below, default off; docs/diagnose.md §4
S14-A): (T5) a magnetometer shift within ½ sample is the base model's alignment remainder, not a candidate
(`base_remainder`); (T7) a gyro-referenced delay (T2) is a candidate only where the rotation model explains
most of the channel's change (`rotation_explained` > ½: not a hand-held accelerometer); (T6) the fitted
correction asks to be judged by the held-out log score's sign test (attribute.significant, (A4'')) — a
delay's residual τ ḣ is motion-locked and small beside a hand's linear acceleration, whose colour and
shape (G1) sees first (07 + 18 ms gyro delay: (A2) −0.00, log score +0.29 nats per sample, every fold > 0).

Injection ranges (RANGES): τ = 5–50 ms (a digital low-pass filter's group delay — a 2nd-order 20–40 Hz
low-pass delays by ~5–10 ms —, or a channel read out on its own schedule or time-stamped by a host over
USB/Bluetooth, tens of ms), never below one sample period (`injection_range_s`: the relevance threshold;
at 100 Hz τ = 10–50 ms), channel acc (p = 0.5) or gyr (0.5). Not mag: the magnetometer's lag behind
the gyro is part of the base model (diagnose/fit.py (B3), as of `imugraph calibrate`'s default model), so
a delayed magnetometer is not an effect the base model leaves out; the fit still searches mag (a lag the
base model's whole-sample alignment left).
"""

from __future__ import annotations

import numpy as np

from imugraph.calibration.alignment import estimate_mag_delay
from imugraph.geometry import skew
from imugraph.diagnose.effects.base import (Correction, Effect, check_train, gyro_exact, gyro_refit, noise_scale,
                                             replace_session, shift_signal)

RANGES = {"tau_ms": (5.0, 50.0), "channel_p": {"acc": 0.5, "gyr": 0.5}}
MAX_DELAY_S = 0.1            # search range of the gyro-referenced delay (T2), ± s
MAG_REMAINDER_OUT = True     # (T5): a magnetometer shift within ½ sample is the base model's, not a candidate
LOG_SCORE_SIGNIFICANCE = True    # (T6): significant by the held-out log score's sign test (A4'')
ROTATION_CHECK = True        # (T7): a gyro-referenced delay only where rotation is most of the channel's change
# S15 (default since S15, `DiagnoseOptions.gyro_delay_model`; docs/diagnose.md §S15): the extended model of a GYRO delay
# (T8) changes the gyro data only in the refit (the base `Correction.corrected` also moved acc and mag by the
# keyframes-fixed trajectory change h(R̂) − h(R'), pulling the data back to the old trajectory), and (T9)
# keeps the base model's magnetometer lag τ_m as measured against the gyro: with the gyro's delay τ removed
# the field lags the corrected gyro by τ_m + τ, re-aligned by whole samples (`field_after_gyro_shift`).
GYRO_DELAY_MODEL = True
SIZE_CONFIDENCE = True       # S20-V (T12): relevant only when |τ| exceeds 1 sample beyond its folds' SE (default since S20)
SIZE_Z = 1.645               # (T12): one-sided 95 % normal quantile
# S20-W (T13, `DiagnoseOptions.shift_prediction`, default off; docs/diagnose.md §S20-W): an acc/mag delay's residual is
# y_j − h_c(x(t_j − τ)) — the smooth PREDICTION shifted —, not the data shifted by linear interpolation, which for a
# fractional τ (fraction φ) averages neighbouring samples: white noise then drops to ((1−φ)² + φ²) σ² (½ σ² at φ = ½)
# and the held-out log score (A4) rises with no delay in the data at all (the gaittoolbox foot, §S20-W).
SHIFT_PREDICTION = False
SHIFT_PREDICTION_CHANNELS = ("acc", "mag")   # (T13) applies to these; ("acc",): the field keeps the data shift, whose
                                             # sub-sample part the base model's whole-sample lag leaves (BROAD 04, §S20-W)


def injection_range_s(rate_hz: float) -> tuple[float, float]:
    """(τ_lo, τ_hi) of the injection, s: RANGES["tau_ms"] with the lower end raised to one sample period
    (the relevance threshold of `size`) and the upper end to two, so that every injected delay is above
    relevance at any rate (100 Hz: 10–50 ms); at BROAD's 285.7 Hz (3.5 ms per sample) RANGES unchanged."""
    lo, hi = (1e-3 * float(v) for v in RANGES["tau_ms"])
    period = 1.0 / max(float(rate_hz), 1e-9)
    return max(lo, period), max(hi, 2.0 * period)


def _cost(fit, res: dict, train: np.ndarray, channels) -> float:
    total = 0.0
    for c in channels:
        z = res[c][train] / fit.sigma[c]
        total += float(np.nansum(z**2))
    return total


def _relative_cost(fit, res: dict, train: np.ndarray, channels) -> float:
    """Σ_c cost_c(res) / cost_c(base): each channel's whitened cost relative to the base fit's, so that the
    gyro (whose keyframe residual has a tiny σ) does not outweigh a magnetometer that a shift explains."""
    return sum(_cost(fit, res, train, [c]) / max(_cost(fit, fit.residuals, train, [c]), 1e-30)
               for c in channels)


def base_remainder(tau_s: float, rate_hz: float) -> bool:
    """True when a magnetometer shift τ is within the base model's own alignment remainder (T5): the base
    model puts the field on the gyro's time base by whole samples (diagnose/fit.py (B3)), which leaves up
    to ½ sample period, τ_f, that (B3') puts in the prediction. A shift |τ| ≤ ½ sample is therefore that
    remainder, part of the base model, not a channel timing the model leaves out; it is also below
    relevance (`size`: 1 sample) by construction, so when it wins the candidates (its whitened cost falls
    by 14–22 % on the fast crops, docs/diagnose.md §5) it hides a relevant delay of acc or gyr, which
    then never reaches the verdict."""
    return abs(float(tau_s)) * float(rate_hz) <= 0.5


def gyro_referenced_delays(fit, train: np.ndarray) -> dict:
    """channel → τ (s) from the raw measurements and the gyro only (T2), training samples only: acc and
    mag by `imugraph.calibration.alignment.estimate_mag_delay` (a constant
    nav-frame vector seen from the turning body obeys ẏ = y × ω; the delay is the gyro shift that best
    explains the channel's change over 40 ms windows, a free 3×3 map absorbing scale and misalignment) —
    gravity for acc, the field with the fitted hard iron removed for mag; gyr: −τ_acc (a late gyro makes
    the accelerometer early). Independent of the fitted trajectory, which a delayed channel bends (the
    first-order (T1) then underestimates τ: 8.9 ms found for 21 ms injected into an accelerometer)."""
    s = fit.session
    w = s.gyr - np.nan_to_num(fit.b_gyr_bias)
    hide = ~np.asarray(train, bool)[:, None]
    out = {}
    try:
        D = np.asarray(fit.calibration.D, float)
        m = np.linalg.solve(D, (s.mag - np.asarray(fit.calibration.o, float)).T).T
        for c, y in (("mag", m), ("acc", s.acc)):
            y = np.where(hide, np.nan, y)
            tau = estimate_mag_delay(s.t, y, w, max_delay_s=MAX_DELAY_S)
            if not ROTATION_CHECK or rotation_explained(s.t, y, w, tau) > 0.5:                  # (T7)
                out[c] = tau
        if "acc" in out:
            out["gyr"] = -out["acc"]
    except (np.linalg.LinAlgError, ValueError):
        return {}
    return out


def rotation_explained(t: np.ndarray, y: np.ndarray, b_gyr: np.ndarray, tau_s: float, window_s: float = 0.04,
                       max_rows: int = 4000) -> float:
    """Fraction of a channel's change over `window_s` windows that the rotation model of (T2) explains at
    the delay τ (the model `estimate_mag_delay` fits, at one lag: Δy_j ≈ [y_j]× A ΔΩ_j(τ), A a free 3×3):

        E = 1 − Σ_j |Δy_j − [y_j]× Â ΔΩ_j(τ)|² / Σ_j |Δy_j|²                                        (T7)

    (T2) holds when the channel sees a CONSTANT nav-frame vector from the turning body; its delay is a
    candidate only when that model is most of what the channel does (E > ½). Measured (60 s crops): the
    accelerometer of simulations without linear acceleration E = 0.98; hand-held BROAD 01, 02, 06, 07
    E = 0.07–0.25, where (T2) gave +36, −8.1, −17 ms and 0 (no optimum) against the accelerometer's own
    ≈ −1…−5 ms — its hand's linear acceleration, not gravity, is most of the change; the field
    E = 0.69–0.98 on every crop. Rows with a non-finite end (held-out blocks) are left out."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    step = float(np.median(np.diff(t)))
    h = max(1, int(round(0.5 * window_s / step)))
    mid = np.arange(h, len(t) - h)
    mid = mid[np.linspace(0, mid.size - 1, min(mid.size, max_rows)).round().astype(int)] if mid.size else mid
    lo, hi = mid - h, mid + h
    dy = y[hi] - y[lo]
    omega = np.concatenate([np.zeros((1, 3)), np.cumsum(np.nan_to_num(b_gyr[:-1]) * np.diff(t)[:, None], axis=0)])
    d_om = np.stack([np.interp(t[hi] - tau_s, t, omega[:, i]) - np.interp(t[lo] - tau_s, t, omega[:, i])
                     for i in range(3)], axis=1)                                          # ΔΩ_j(τ)
    ok = np.all(np.isfinite(dy), axis=1) & np.all(np.isfinite(y[mid]), axis=1)
    if ok.sum() < 20:
        return 0.0
    A = np.einsum("nik,nl->nikl", skew(y[mid][ok]), d_om[ok]).reshape(-1, 9)           # [y_j]× ⊗ ΔΩ_jᵀ
    b = dy[ok].reshape(-1)
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    return float(1.0 - np.sum((b - A @ theta) ** 2) / max(float(np.sum(b * b)), 1e-300))


def _first_order_floor(fit, r0: dict, J: dict, train: np.ndarray, channels) -> float:
    """A lower bound of the relative cost (`_relative_cost`) of ANY gyro shift τ, from its first-order
    form r(τ) ≈ r₀ + τ J (base (E1)–(E3), J = ∂r/∂τ), which costs one affine refit instead of the exact
    re-integration of every candidate:

        q(τ) = Σ_c |W_c (r₀_c + τ J_c)|² / cost_c(base),   q_min = q(0) − β²/α                       (T4)

    (α, β the quadratic's coefficients). The exact relative cost differs from q(τ) by less than the whole
    change q(0) − q(τ) (measured: < 6 % of it on BROAD 01 for τ up to 20 ms; the exact gyro evaluation's
    difference from (E1)–(E3) is up to ~25 % of the residual change, trajectory.gyro_exact), so no gyro
    shift costs less than min(q(0), 2 q_min − q(0)). When that exceeds the best acc/mag candidate the
    gyro candidates (two Gauss–Newton steps and two exact evaluations, ~0.4 s each on a 3-minute session)
    cannot win and are not evaluated: on the base fit they never do (a gyro shift with the keyframes
    fixed fights the keyframes, which followed the gyro: q ≥ q(0))."""
    alpha = beta = q0 = 0.0
    for c in channels:
        ok = train & np.all(np.isfinite(r0[c]), axis=1) & np.all(np.isfinite(J[c]), axis=1)
        sg = np.asarray(fit.sigma[c], float)
        norm = max(_cost(fit, fit.residuals, train, [c]), 1e-30)
        z, j = r0[c][ok] / sg, J[c][ok] / sg
        alpha += float(np.sum(j * j)) / norm
        beta += float(np.sum(z * j)) / norm
        q0 += float(np.sum(z * z)) / norm
    q_min = q0 - beta**2 / alpha if alpha > 0 else q0
    return min(q0, 2.0 * q_min - q0)


def field_after_gyro_shift(fit, tau: float):
    """(T9) The field of `fit.session` re-aligned to a gyro corrected by τ (y'_g(t) = y_g(t + τ)), or None
    when no whole-sample change is needed. The base model's τ_m (`fit.info["mag_delay_s"]`, B3) is the
    field's lag behind the RECORDED gyro; a gyro late by τ_g and a field late by τ_0 give τ_m = τ_0 − τ_g,
    so against the corrected gyro the field lags by τ_m + τ. The session's field was shifted by
    n_0 = round(τ_m/Δt) rows; it needs n_1 = round((τ_m + τ)/Δt): `undelay_magnetometer` by n_1 − n_0 rows
    (whole samples, as the base model; rows shifted in from beyond the ends are NaN)."""
    from imugraph.calibration.alignment import undelay_magnetometer

    s = fit.session
    dt = float(np.median(s.dt))
    tau_m = float(fit.info.get("mag_delay_s", 0.0) or 0.0)
    extra = int(np.round((tau_m + tau) / dt)) - int(np.round(tau_m / dt))
    return None if extra == 0 else undelay_magnetometer(s.t, s.mag, extra * dt)


class TimeOffsetCorrection(Correction):
    def raw_residuals(self, fit) -> dict:
        c, tau = self.params["channel"], self.params["tau_s"]
        s = fit.session
        y = getattr(s, c)
        y_new = shift_signal(s.t, y, -tau)                                           # y'(t) = y(t + τ)
        if c == "gyr":
            out = gyro_exact(fit, np.nan_to_num(y_new - y))
            mag = field_after_gyro_shift(fit, tau) if GYRO_DELAY_MODEL else None       # (T9)
            if mag is not None:
                out["mag"] = out["mag"] + (mag - s.mag)      # h_mag does not depend on the data: y changes only
            return out
        if SHIFT_PREDICTION and c in SHIFT_PREDICTION_CHANNELS:                        # (T13)
            out = {k: v.copy() for k, v in fit.residuals.items()}
            out[c] = y - shift_signal(s.t, fit.predicted()[c], tau)        # r = y(t) − h(t − τ), data untouched
            return out
        return fit.residuals_with(**{c: y_new})

    def corrected(self, fit) -> dict:
        """The data with the delay removed, for the refit. (T8) a gyro delay: the gyro shifted, acc as recorded
        and the field re-aligned (T9) — not the base rule's y + (r' − r) for acc and mag, which for a gyro
        change is the keyframes-fixed trajectory's change, not the effect's."""
        if not (GYRO_DELAY_MODEL and self.params["channel"] == "gyr"):
            return super().corrected(fit)
        s = fit.session
        out = {"gyr": shift_signal(s.t, s.gyr, -self.params["tau_s"])}
        mag = field_after_gyro_shift(fit, self.params["tau_s"])
        if mag is not None:
            out["mag"] = mag
        return out


class TimeOffset(Effect):
    name = "time_offset"
    channel = "mag"
    windowed = False
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """Delay one channel by τ. strength: τ in s (default random in RANGES); the channel is random."""
        tau = float(strength) if strength is not None else float(rng.uniform(*injection_range_s(session.rate)))
        names, p = zip(*RANGES["channel_p"].items())
        c = str(rng.choice(names, p=p))
        y = shift_signal(session.t, getattr(session, c), tau)
        truth = {"params": {"channel": c, "tau_s": tau}, "t_start": None, "t_end": None}
        return replace_session(session, **{c: y}, name_suffix="+time_offset",
                               meta={"injected": {self.name: truth}}), truth

    def fit_fold(self, fit, train, window, full) -> Correction:
        """S17-H (T11), `attribute.FOLD_FIXED_STRUCTURE`: a cross-validation fold's fit of the model the
        all-sample fit `full` chose — its channel held, τ refitted on the fold's training samples. The
        channel is the model's structure (which sensor is late), not a parameter: left free, a fold can
        land on another channel's near-zero candidate and score a different model than the one named
        (harness seed 2 case 008, 06 + 10.6 ms gyro delay: folds' τ 4.3–4.5 samples on acc, one fold 0.03 on
        another candidate, its log score −0.01: (A4'') failed on the fold that fitted something else)."""
        return self.fit(fit, train, window, candidates=(full.channel,))

    def fit(self, fit, train, window=None, candidates=("mag", "acc", "gyr")) -> Correction:
        train = check_train(fit, train)
        s = fit.session
        pred = fit.predicted()
        channels = ("gyr", "acc", "mag")
        base_cost = _cost(fit, fit.residuals, train, channels)
        best = None
        ref = gyro_referenced_delays(fit, train)                                    # (T2)
        for c in candidates:
            tau = 0.0
            for _ in range(2):
                r = TimeOffsetCorrection(self.name, {"channel": c, "tau_s": tau}, 2).raw_residuals(fit)
                if c == "gyr":
                    y_tau = shift_signal(s.t, s.gyr, -tau)
                    r1 = gyro_refit(fit, np.nan_to_num(np.gradient(y_tau, s.t, axis=0)))[0]
                    J = {k: r1[k] - fit.residuals[k] for k in channels}              # ∂r/∂τ (affine refit)
                    r_base = r
                else:
                    hdot = np.gradient(pred[c], s.t, axis=0)
                    J = {c: hdot}                                                    # r(τ+δ) ≈ r + δ ḣ
                    r_base = r
                num = den = 0.0
                for k, Jk in J.items():
                    ok = train & np.all(np.isfinite(r_base[k]), axis=1) & np.all(np.isfinite(Jk), axis=1)
                    sg = np.asarray(fit.sigma[k], float)
                    num += float(np.sum((Jk[ok] / sg) * (r_base[k][ok] / sg)))
                    den += float(np.sum((Jk[ok] / sg) ** 2))
                if c == "gyr" and tau == 0.0 and best is not None and \
                        _first_order_floor(fit, r_base, J, train, channels) > best[0]:
                    tau = None                # no gyro shift can beat the best candidate: skip (T4)
                    break
                tau = float(np.clip(tau - num / max(den, 1e-30), -0.2, 0.2))
            if tau is None:
                continue
            for tau_c in (tau, ref.get(c)):           # Gauss–Newton on (T1) and the gyro-referenced (T2)
                if tau_c is None or (MAG_REMAINDER_OUT and c == "mag" and base_remainder(tau_c, s.rate)):
                    continue
                corr = TimeOffsetCorrection(self.name, {"channel": c, "tau_s": float(tau_c)}, 2, channel=c)
                res = corr.raw_residuals(fit)       # (a gyro shift re-integrates the trajectory: kept, not redone)
                cost = _relative_cost(fit, res, train, channels)
                if best is None or cost < best[0]:
                    best = (cost, corr, res)
        if best is None:    # a held channel (fit_fold) whose every τ is the base model's remainder (T5): τ = 0, a
            #                 fold that does not support the named model scores ≈ 0 and fails (A4'') (review R4)
            c = candidates[0]
            corr = TimeOffsetCorrection(self.name, {"channel": c, "tau_s": 0.0}, 2, channel=c)
            best = (None, corr, corr.raw_residuals(fit))
        _, corr, res = best
        if corr.channel == "gyr":
            corr.deltas["d_omega"] = np.nan_to_num(shift_signal(s.t, s.gyr, -corr.params["tau_s"]) - s.gyr)
        corr.params["train_cost_reduction"] = float(1.0 - _cost(fit, res, train, channels) / max(base_cost, 1e-30))
        corr.deltas["noise_scale"] = noise_scale(fit, res, train, [corr.channel])
        if LOG_SCORE_SIGNIFICANCE:
            corr.params["significance"] = "log_score"                                  # (T6)
        return corr


    def refit(self, real, rounds: int = 2, window=None):
        """Full refit (docs/diagnose.md §3 (F1)). Default: the alternation of imugraph.diagnose.refit. With
        GYRO_DELAY_MODEL (S15, (T10)): the alternation's map g(τ) = τ fitted against θ(τ) (θ(τ): the base
        model refitted to the data with τ removed) converges linearly and slowly (sim00 + 5.9 ms gyro delay,
        τ over rounds 2.3, 3.7, 4.6, 5.2 ms), so its fixed point τ = g(τ) is found by the secant method on
        f(τ) = g(τ) − τ from τ_0 = 0 (the base fit), rounds + 1 refits of the base model:

            τ_{r+1} = τ_r − f(τ_r) (τ_r − τ_{r−1}) / (f(τ_r) − f(τ_{r−1}))                          (T10)

        (the first step τ_1 = g(0), as the alternation; a step at most 4 |f(τ_r)|; the plain step g(τ_r)
        when the fitted channel changes between rounds). Only when the first round's candidate is the gyro:
        an acc or mag delay keeps the plain alternation (with the secant, BROAD 04 + an injected gyro scale, harness
        case 010, converged to an accelerometer lead of −9.7 ms, 2.8 samples, preferred by the log score in
        every fold: the hand-held accelerometer's apparent lead, docs/diagnose.md §4 S14-A, made the verdict).
        Returns (θ* on the original data, info)."""
        from imugraph.diagnose.refit import on_session, refit_effect
        from imugraph.diagnose.fit import fit_simulation

        if not GYRO_DELAY_MODEL:
            return refit_effect(self, real, rounds, window)
        train = np.ones(real.n, bool)
        cur, tau_in, pts, info = real, 0.0, [], {"rounds": []}
        for _ in range(rounds + 1):
            view = real if cur is real else on_session(cur, real.session)
            corr = self.fit(view, train)
            ch, g = corr.params["channel"], float(corr.params["tau_s"])
            if cur is real and ch != "gyr":       # (T8)–(T10) are a GYRO delay's model: acc/mag as before
                return refit_effect(self, real, rounds, window)
            info["rounds"].append({"params": dict(corr.params), "tau_in_s": tau_in, "t_start": None, "t_end": None})
            pts.append((ch, tau_in, g))
            nxt = g
            if len(pts) >= 2 and pts[-2][0] == ch:                                          # (T10)
                (_, a0, g0), (_, a1, g1) = pts[-2], pts[-1]
                f0, f1 = g0 - a0, g1 - a1
                if f1 != f0 and a1 != a0:
                    step = -f1 * (a1 - a0) / (f1 - f0)
                    nxt = a1 + float(np.clip(step, -4 * abs(f1), 4 * abs(f1)))
            if abs(nxt - tau_in) < 0.05 / real.session.rate:   # a twentieth of a sample: θ(τ_in) stands
                info["converged"] = True
                break
            new = TimeOffsetCorrection(self.name, {"channel": ch, "tau_s": nxt}, 2, channel=ch).corrected(view)
            cur = fit_simulation(replace_session(real.session, **new), cur)
            cur.info["mag_delay_s"] = real.info.get("mag_delay_s", 0.0)
            tau_in = nxt
        info["window"] = None
        info["changed"] = cur is not real
        return on_session(cur, real.session), info

    def size(self, corr, fit) -> dict:
        """|τ| in samples (relevance: ≥ 1 sample period; a shorter delay is below the time resolution)."""
        return {"value": abs(float(corr.params["tau_s"])) * fit.session.rate, "threshold": 1.0,
                "unit": "samples"}

    def size_bound(self, size: dict, fold_sizes) -> dict:
        """S20-V (T12), SIZE_CONFIDENCE: relevance asks that |τ| reach one sample beyond its estimation
        uncertainty, the delete-one-block jackknife over the K cross-validation folds (contiguous blocks, so
        the motion's own correlation is in it; τ_k fitted without block k, `EffectResult.fold_sizes`):

            SE² = (K − 1)/K Σ_k (τ_k − τ̄)²,   relevant ⇔ |τ| ≥ 1 sample + z SE  (z = SIZE_Z)      (T12)

        A sensor whose channels are skewed by about a sample (the BROAD unit's accelerometer leads its gyro
        by 0.9–1.35 samples on every rotation trial) is then not named for a delay it cannot be shown to
        exceed the time resolution by. Without the flag or with < 3 finite fold sizes: `size` unchanged."""
        tau_k = np.asarray([x for x in (fold_sizes or []) if np.isfinite(x)], float)
        if not SIZE_CONFIDENCE or len(tau_k) < 3:
            return size
        se = float(np.sqrt((len(tau_k) - 1) / len(tau_k) * np.sum((tau_k - tau_k.mean()) ** 2)))
        return {**size, "se": se, "threshold": float(size["threshold"]) + SIZE_Z * se}             # (T12)


EFFECT = TimeOffset()
