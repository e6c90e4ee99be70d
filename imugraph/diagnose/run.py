"""The whole diagnosis of one single-IMU session: fit, simulate, gap, localise, attribute.

    1. fit the base model to the recording (`fit.fit_base`);
    2. draw two simulations from the fit (same motion, fitted parameters and noise) and fit each of them
       the same way (`fit.fit_simulation`): A is the reference, B an independent draw that gives the
       statistic's noise floor (gap of B against A: "null");
    3. gap per channel (real vs A, `gap.gap`), gap-vs-time curves (real vs A and B vs A) and locations
       (`gap.localise`);
    4. attribution over the effect library (`attribute.attribute`, `attribute.verdict`);
    5. the winning effect refitted on all samples gives the residuals "after" for the report.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from imugraph.diagnose.attribute import (NONE, AttributionOptions, EffectResult, attribute, fold_masks,
                                         verdict)
from imugraph.diagnose.fit import Fit, base_options, fit_base, fit_simulation, simulate_from_fit
from imugraph.diagnose.gap import CHANNELS, GapCurve, GapOptions, gap, gap_curve, localise
from imugraph.io.session import Session


@dataclass(frozen=True)
class DiagnoseOptions:
    """Settings of one diagnosis.

    Attributes:
        keyframe_hz: orientation states per second of the base fit.
        seed: seed of the simulations' noise.
        effects: names of the effects to try (None: the whole library).
        window_hints: hand the located window of a channel to that channel's windowed effects.
        gap / attribution: the statistic's and the attribution's settings.
        joint_gyro: gyro_scale and gyro_bias_drift fitted jointly with the trajectory (effects/joint.py
            (J1)) instead of the keyframes-fixed first-order fit; None: the module flag `joint.ENABLED`
            (default True). Scored by their own held-out cost (J5) when `attribution.own_score`.
        subsample_lag: the magnetometer's sub-sample lag in the base model's prediction (fit.py (B3'));
            None: the module flag `fit.SUBSAMPLE_LAG` (default False).
        timing_rules: time_offset's S14-A rules (effects/time_offset.py (T5) field remainder out, (T6) held-out
            log-score significance, (T7) rotation check of the gyro-referenced delay); None: the module flags
            (default True since session 14; False: as before S14-A).
        drift_basis: gyro_bias_drift's basis, "legendre" (the cubic (D1)) or "spline" (knots every 10 s
            (D2), effects/gyro_bias_drift.py, docs/diagnose.md §4 S14-B); None: the module's `BASIS`
            (default "legendre").
        gyro_delay_model: S15 (docs/diagnose.md §S15): time_offset's extended model of a gyro delay (T8)–(T10)
            — the refit changes the gyro data only, keeps the base model's field lag against the corrected
            gyro, and finds the alternation's fixed point by the secant method; None: the module flag
            `time_offset.GYRO_DELAY_MODEL` (default True since session 15).
        magnet_ramps: S15: magnetic_disturbance's window field with fitted linear ramps at its edges (R1)
            instead of a step; None: the module flag `magnetic_disturbance.RAMPS` (default True since session 15).
        magnet_step_refit: S16-E (M3'): magnetic_disturbance's step search repeated on the residual of the (M1)
            fit of the windows found so far; None: the module flag `magnetic_disturbance.STEP_REFIT` (default True since session 16).
        saturation_censor: S16-E (C1'): a gyro sample on a rail censored in saturation's residuals (no residual
            where the fitted rate is beyond the rail); None: the module flag `saturation.CENSOR_GYRO` (default True since session 16).
        saturation_area: S16-E (C1''): the censored gyro values estimated per keyframe interval against the
            keyframes (≥ the rail); None: the module flag `saturation.CENSOR_AREA` (default False).
        vibration_band_windows: S16-F (V3)–(V4): vibration's windows re-localised on the fitted band, and kept
            only when their excess power above the motion band lies mostly in it (a broadband transient of the
            host is not a vibration); None: the module flag `vibration.BAND_WINDOWS` (default True since session 16).
        fold_fixed_structure: S17-H (T11): an effect's cross-validation folds refit its parameters with the
            discrete structure of its all-sample fit held (time_offset: the late channel; `Effect.fit_fold`);
            None: the module flag `attribute.FOLD_FIXED_STRUCTURE` (default True since session 17).
        local_check: S17-H (V'): a localised verdict leaves when a significant, relevant global effect on its
            channel scores at least its held-out log score on its support (imugraph/diagnose/local_check.py);
            None: the module flag `local_check.LOCAL_CHECK` (default False).
        magnet_intermittent: S20-M (M6): magnetic_disturbance's windows for an intermittent disturbance (a
            stationary magnet visited several times): up to 8 windows, each passing (M3)'s test, kept when the
            edge refinement shortens them (MagneticDisturbance.find_windows); None: the module flag
            `magnetic_disturbance.INTERMITTENT` (default False).
        magnet_visit_drift: S20-M (M7): magnetic_disturbance's window field drifting through the window (Legendre
            orders 1–2 of Δo_w and Δn_w, effects/magnet_intermittent.py); None: the module flag
            `magnetic_disturbance.VISIT_DRIFT` (default False).
        vibration_motion_check: S20-V (V6): vibration is relevant only when its band RMS also exceeds the band RMS
            the measured angular motion explains at a hand's lever arm (effects/vibration.py); None: the module
            flag `vibration.MOTION_CHECK` (default True since session 20).
        timing_confidence: S20-V (T12): time_offset is relevant only when |τ| ≥ 1 sample + z·SE, SE the folds'
            jackknife (effects/time_offset.py `size_bound`); None: the module flag `time_offset.SIZE_CONFIDENCE`
            (default True since session 20).
        timestamp_jitter: S20-T: the timestamp_jitter effect (effects/timestamp_jitter.py: host receive stamps
            re-timed on a fitted sample clock) added to the library; None: the module flag
            `timestamp_jitter.ENABLED` (default True since session 20; False drops it from the library).
        refit_hold_noise: S20-Mb: the full refit's (F1) rounds (refit.refit_effect) hold the base fit's noise
            levels instead of re-estimating them, so that θ* differs from the base fit only by what the effect
            removed from the data; None: the module flag `refit.HOLD_NOISE` (default False).
        refit_accelerate: S20-Mb (F2): the full refit's alternation runs 4 rounds and then jumps to the Aitken
            extrapolation of its corrected data (its slow linear convergence left θ* far from the fixed point);
            None: the module flag `refit.ACCELERATE` (default False).
        nested_check: S20-W (V''): an effect significant only by the log-score route leaves the verdict unless it
            keeps its held-out log score on top of a relevant effect on its channel with a larger one (a nested
            test, imugraph/diagnose/nested.py); None: the module flag `nested.NESTED_CHECK` (default False).
        shift_prediction: S20-W (T13): time_offset's acc/mag residual is y − h(t − τ) (the prediction shifted) instead
            of the data shifted by linear interpolation (which smooths the noise for a fractional τ); None: the
            module flag `time_offset.SHIFT_PREDICTION` (default False).
        whitening_jacobian: S20-W (L3): the held-out log score of a whitened residual (linear_acceleration, vibration)
            charged its filter's Jacobian −(1/n) ln|det W| (imugraph/diagnose/nested.py `log_det`); None: the module
            flag `attribute.WHITENING_JACOBIAN` (default False).
    """

    keyframe_hz: float = 5.0
    seed: int = 0
    effects: tuple | None = None
    window_hints: bool = False
    joint_gyro: bool | None = None
    subsample_lag: bool | None = None
    timing_rules: bool | None = None
    drift_basis: str | None = None
    gyro_delay_model: bool | None = None
    magnet_ramps: bool | None = None
    magnet_step_refit: bool | None = None
    saturation_censor: bool | None = None
    saturation_area: bool | None = None
    vibration_band_windows: bool | None = None
    fold_fixed_structure: bool | None = None
    local_check: bool | None = None
    magnet_intermittent: bool | None = None
    magnet_visit_drift: bool | None = None
    vibration_motion_check: bool | None = None
    timing_confidence: bool | None = None
    timestamp_jitter: bool | None = None
    refit_hold_noise: bool | None = None
    refit_accelerate: bool | None = None
    nested_check: bool | None = None
    shift_prediction: bool | None = None
    whitening_jacobian: bool | None = None
    gap: GapOptions = field(default_factory=GapOptions)
    attribution: AttributionOptions = field(default_factory=AttributionOptions)


@dataclass
class Diagnosis:
    """Result of `diagnose` (diagnosis.json via `to_json`)."""

    verdict: str
    gap: dict                 # channel → excess of the real gap over the noise floor, max(0, raw − null)
    gap_raw: dict             # channel → (G1) real vs simulation A
    null_gap: dict            # channel → (G1) simulation B vs simulation A
    null_fold_gap: dict
    locations: list
    effects: list
    real: Fit
    sim: Fit
    curve: GapCurve
    null_curve: dict
    residuals_after: dict | None
    timing: dict

    def to_json(self) -> dict:
        """The DESIGN.md `diagnosis.json` contract, plus the noise floor, the channel σ and timings."""
        return {"verdict": self.verdict, "gap": dict(self.gap), "gap_raw": dict(self.gap_raw),
                "locations": list(self.locations),
                "effects": [r.as_dict() for r in self.effects],
                "null_gap": dict(self.null_gap), "null_fold_gap": dict(self.null_fold_gap),
                "sigma": {c: np.asarray(self.real.sigma[c]).tolist() for c in CHANNELS},
                "base_model": {"mag_delay_s": float(self.real.info.get("mag_delay_s", 0.0)),
                               "mag_subsample_s": float(self.real.info.get("mag_subsample_s", 0.0))},
                "session": {"name": self.real.session.name, "source": self.real.session.source,
                            "samples": self.real.n, "rate_hz": self.real.session.rate},
                "timing_s": dict(self.timing)}


def load_effects(names=None) -> dict:
    """name → Effect from `imugraph.diagnose.effects.EFFECTS` (empty when the library is absent).

    Raises:
        SessionError: a requested name is not in the library.
    """
    try:
        from imugraph.diagnose.effects import EFFECTS
    except ImportError:
        EFFECTS = {}
    if names is None:                     # the library without the effects switched off (S20-T timestamp_jitter)
        return {n: e for n, e in EFFECTS.items() if getattr(e, "enabled", True)}
    from imugraph.errors import SessionError

    missing = [n for n in names if n not in EFFECTS]
    if missing:
        raise SessionError("--effects", "effects", ", ".join(missing), f"names among {sorted(EFFECTS)}")
    return {n: EFFECTS[n] for n in names}


def null_fold_gap(null: Fit, sim: Fit, sigma: dict, folds: list, gap_opt: GapOptions) -> dict:
    """channel → sample-weighted mean over the folds of the null gap (noise floor at fold size)."""
    rate = null.session.rate
    out = {c: 0.0 for c in CHANNELS}
    total = sum(float(f.sum()) for f in folds) or 1.0
    for f in folds:
        g = gap(null.residuals, sim.residuals, sigma, rate, f, gap_opt, fits=(null, sim))
        for c in CHANNELS:
            out[c] += g[c] * float(f.sum()) / total
    return out


@contextmanager
def model_switches(options: DiagnoseOptions):
    """The options' model switches (the table below: option field → module flags) set on their modules for the
    duration of a diagnosis, restored afterwards, also on an error (None: left as the module has them)."""
    import importlib

    from imugraph.errors import SessionError

    if options.drift_basis is not None and options.drift_basis not in ("legendre", "spline"):
        raise SessionError("<options>", "drift_basis", repr(options.drift_basis), "'legendre' or 'spline'")
    # (option field, module, module flags it sets, converter): the boolean ones take bool(value)
    pkg = "imugraph.diagnose."
    table = [("vibration_band_windows", "effects.vibration", ("BAND_WINDOWS",), bool),
             ("vibration_motion_check", "effects.vibration", ("MOTION_CHECK",), bool),
             ("timing_confidence", "effects.time_offset", ("SIZE_CONFIDENCE",), bool),
             ("fold_fixed_structure", "attribute", ("FOLD_FIXED_STRUCTURE",), bool),
             ("timestamp_jitter", "effects.timestamp_jitter", ("ENABLED",), bool),
             ("refit_hold_noise", "refit", ("HOLD_NOISE",), bool),
             ("refit_accelerate", "refit", ("ACCELERATE",), bool),
             ("local_check", "local_check", ("LOCAL_CHECK",), bool),
             ("nested_check", "nested", ("NESTED_CHECK",), bool),
             ("shift_prediction", "effects.time_offset", ("SHIFT_PREDICTION",), bool),
             ("whitening_jacobian", "attribute", ("WHITENING_JACOBIAN",), bool),
             ("gyro_delay_model", "effects.time_offset", ("GYRO_DELAY_MODEL",), bool),
             ("magnet_ramps", "effects.magnetic_disturbance", ("RAMPS",), bool),
             ("saturation_area", "effects.saturation", ("CENSOR_AREA",), bool),
             ("saturation_censor", "effects.saturation", ("CENSOR_GYRO",), bool),
             ("magnet_step_refit", "effects.magnetic_disturbance", ("STEP_REFIT",), bool),
             ("magnet_intermittent", "effects.magnetic_disturbance", ("INTERMITTENT",), bool),
             ("magnet_visit_drift", "effects.magnetic_disturbance", ("VISIT_DRIFT",), bool),
             ("drift_basis", "effects.gyro_bias_drift", ("BASIS",), str),
             ("timing_rules", "effects.time_offset", ("MAG_REMAINDER_OUT", "LOG_SCORE_SIGNIFICANCE",
                                                      "ROTATION_CHECK"), bool),
             ("joint_gyro", "effects.joint", ("ENABLED",), bool),
             ("subsample_lag", "fit", ("SUBSAMPLE_LAG",), bool)]
    saved = []                                   # (module, flag, old value), restored in reverse order
    try:
        for field_name, module, flags, kind in table:
            value = getattr(options, field_name)
            if value is None:                    # left as the module has it
                continue
            mod = importlib.import_module(pkg + module)
            for flag in flags:
                saved.append((mod, flag, getattr(mod, flag)))
                setattr(mod, flag, kind(value))
        yield
    finally:
        for mod, flag, old in reversed(saved):
            setattr(mod, flag, old)


def diagnose(session: Session, options: DiagnoseOptions = DiagnoseOptions(), effects: dict | None = None,
             progress=None) -> Diagnosis:
    """Diagnose one single-IMU session (module doc).

    Args:
        session: the recording (not modified).
        options: settings.
        effects: name → Effect to try; default `load_effects(options.effects)`.
        progress: optional callable(str) for progress lines.

    Raises:
        SessionError / CalibrationError: the session cannot be fitted.
    """
    with model_switches(options):
        return _diagnose(session, options, effects, progress)


def _diagnose(session: Session, options: DiagnoseOptions, effects: dict | None, progress) -> Diagnosis:
    say = progress or (lambda _m: None)
    timing = {}
    t0 = time.perf_counter()
    say("fitting the base model")
    real = fit_base(session, base_options(options.keyframe_hz))
    timing["fit_real"] = time.perf_counter() - t0
    rng = np.random.default_rng(options.seed)
    t1 = time.perf_counter()
    say("simulating from the fit and fitting the simulations")
    sim = fit_simulation(simulate_from_fit(real, rng, name=f"{session.name}_simA"), real)
    null = fit_simulation(simulate_from_fit(real, rng, name=f"{session.name}_simB"), real)
    timing["fit_simulations"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    gap_opt = options.gap
    g_real = gap(real.residuals, sim.residuals, real.sigma, session.rate, None, gap_opt, fits=(real, sim))
    g_null = gap(null.residuals, sim.residuals, real.sigma, session.rate, None, gap_opt, fits=(null, sim))
    curve_real = gap_curve(real.residuals, sim.residuals, real.sigma, session.t, gap_opt)
    curve_null = gap_curve(null.residuals, sim.residuals, real.sigma, session.t, gap_opt)
    curve, locations = localise(session.t, curve_real, curve_null, gap_opt)
    folds = fold_masks(session.t, options.attribution)
    g_null_fold = null_fold_gap(null, sim, real.sigma, folds, gap_opt)
    timing["gap"] = time.perf_counter() - t2
    say("gap " + ", ".join(f"{c} {g_real[c]:.3f} (null {g_null[c]:.3f})" for c in CHANNELS))
    t3 = time.perf_counter()
    lib = load_effects(options.effects) if effects is None else effects
    hints = None
    if options.window_hints:
        hints = {}
        for loc in locations:                     # best score first: keep the first per channel
            hints.setdefault(loc["channel"], (loc["t_start"], loc["t_end"]))
    excess = {c: (g_real[c] - g_null[c]) / max(g_null[c], 1e-12) for c in CHANNELS}
    results = attribute(real, sim, g_null_fold, lib, options.attribution, gap_opt, hints, say, excess, null=null)
    v = verdict(results, g_null_fold, options.attribution)
    timing["attribution"] = time.perf_counter() - t3
    after = None
    if v != NONE:
        after = _after(lib[v], real, next(r for r in results if r.name == v), hints, options)
    timing["total"] = time.perf_counter() - t0
    say(f"verdict: {v} ({timing['total']:.1f} s)")
    excess = {c: max(0.0, g_real[c] - g_null[c]) for c in CHANNELS}
    return Diagnosis(v, excess, g_real, g_null, g_null_fold, locations, results, real, sim, curve, curve_null,
                     after, timing)


def _after(effect, real: Fit, res: EffectResult, hints, options) -> dict:
    """Residuals of the winning effect's extended model at every sample (the report's "after"): the
    refitted model (imugraph.diagnose.refit) when the effect was refitted, else the first-order fit."""
    from imugraph.diagnose.refit import refit_effect, rescale

    window = (hints or {}).get(effect.channel) if getattr(effect, "windowed", False) else None
    all_ = np.ones(real.n, bool)
    if res.stage == "refit":
        ext, info = res.refit or refit_effect(effect, real, options.attribution.refit_rounds, window)
        return rescale(effect.fit(ext, all_, window=info["window"]).raw_residuals(ext), real, all_)
    return effect.fit(real, all_, window=window).residuals(real)


def best_result(diag: Diagnosis) -> EffectResult | None:
    """The winning effect's result (None when the verdict is "none")."""
    for r in diag.effects:
        if r.name == diag.verdict:
            return r
    return None
