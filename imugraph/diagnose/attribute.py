"""Attribution: which effect of the library explains the gap, judged on held-out time.

For every effect E (channel c_E) and every fold k of a cross-validation over time blocks:

    Ê_k = E.fit(real fit, train = samples outside fold k)                    (refit on the other blocks)
    after_k,c  = gap_c(Ê_k.residuals(real)[fold k], sim residuals[fold k])    (G1 on held-out time only)
    before_k,c = gap_c(real residuals[fold k],        sim residuals[fold k])

Folds are interleaved blocks (block b of length `block_s` belongs to fold b mod K): every fold spans the
whole recording, so an effect confined to a time window has training samples inside it in every fold,
while the samples scored were never used to fit it. Per effect, over the folds (sample-weighted means):

    gap_before = max(0, before_c_E − null_c_E),  gap_after = max(0, after_c_E − null_c_E)
    shrink = 1 − gap_after / gap_before                                                            (A1)
    penalised  = 1 − (gap_after + p · null_c_E · ln(1 + n_params)) / gap_before
                   − Σ_{c ≠ c_E} max(0, after_c − before_c − null_c) / max(before_c − null_c, null_c)   (A2)

null_c is the gap of an independent simulation against the reference simulation at fold size (the
statistic's own sampling noise, its expected value when the data come from the model): gaps are reported
as the excess over it, so the gap of model data is ≈ 0 and a perfect correction shrinks it by 100 %.
Each parameter costs a fraction of the noise floor (BIC-like, logarithmic), and an effect that makes
another channel worse pays for it. Ranking is by (A2).

Localised effects (A3). An effect that claims part of the recording only — a window (magnetic_disturbance,
vibration) or the samples around a rail (saturation): `effect_support` — is scored on the held-out samples
of its support S only, and its "before" is measured against the recording's own gap outside S:

    floor_c = max(null_c(fold ∩ S), gap_c(real, sim; fold ∩ ¬S))                                    (A3)

in place of null_c in (A1)–(A2) (the parameter cost keeps the noise floor null_c(fold ∩ S)). A real
recording is never the base model: its gap is far above the noise floor everywhere (hand-held linear
acceleration, a magnetometer lag), so a localised effect's shrink over the whole recording — or over S
against the noise floor — measures how much of THAT misfit it removes, which it does not claim. (A3)
asks what it does claim: that S differs from the rest of the same recording, and that the correction
removes the difference. Significance compares the raw gap on S with the noise floor on S.

Verdict (V): of the significant and relevant effects, a localised one (support < half the recording)
comes first, then the best (A2) global one: the localised effect explains what sets part of the
recording apart, beyond the misfit it shares with the rest (which a global effect may explain as well).

An effect is significant when its channel's raw gap is well above the noise floor (before_c ≥
`min_gap_ratio` · null_c) and its (A2) ≥ `margin` — or, for an effect scored on its support (A3), when
the held-out log score prefers the extended model on that support, net of a BIC cost, overall and in
every fold (A4''). The log score (imugraph.diagnose.score, (A4)) is a proper scoring rule: removing a real
effect cannot make it worse in expectation, which (G1) after the noise re-estimation can (BROAD 01 +
vibration, docs/diagnose.md §3, §5). Every EffectResult carries it (`loglik_gain`, per channel, per fold).

A gyro effect fitted jointly with the trajectory (DiagnoseOptions.joint_gyro, effects/joint.py) is judged
by its own held-out criterion (`AttributionOptions.own_score`, issue 5 G7): the sign test (A4'') on the
held-out cost of its objective (J5), AND the share (J6) of the base model's held-out excess cost it
removes ≥ `margin` (what (A2) asks, in the estimator's own units); its reported shrink is then (J6).
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass

import numpy as np

from imugraph.diagnose.gap import CHANNELS, GapOptions, gap
from imugraph.diagnose.result import EffectResult  # noqa: F401  (re-exported: its home before)
from imugraph.diagnose.score import GainAccumulator, OwnCostAccumulator, clearly_better
from imugraph.diagnose.support import (MIN_SUPPORT_S, SUPPORT_PAD_S, effect_support,  # noqa: F401  (re-exported:
                                       scored_apart)                                    # their home before)
from imugraph.folds import held_out_masks

NONE = "none"


@dataclass(frozen=True)
class AttributionOptions:
    """Settings of the attribution.

    Attributes:
        n_folds: number of cross-validation folds.
        block_s: length of the interleaved time blocks, s.
        param_penalty: p in (A2), multiples of the null gap per ln(1 + n_params).
        margin: minimum penalised shrink (A2) of the best effect for a verdict other than "none".
        min_gap_ratio: the winning channel's gap must exceed this multiple of its null gap.
        refit_top: number of best screened effects given the full refit (0: screening only).
        refit_rounds: rounds of the alternation (imugraph.diagnose.refit).
        own_score: an effect whose fit reports its own held-out scores (the joint gyro estimator) is
            significant by the sign test (A4'') of "cost" ((J5): its objective (J1) on held-out rows, AND
            the share (J6) of the base model's excess cost it removes ≥ `margin`, as (A2)) or
            "logscore" ((J5'): (A4) of the two (J1) solutions) instead of (A2)/(A4); "": as before G7.
        joint_refit: give a jointly fitted gyro effect the stage-2 alternation (False, the default: its
            screening, already a joint fit of the effect and the trajectory, stands — about half its CPU; the
            same verdicts on the harness, docs/diagnose.md §4 G7).
    """

    n_folds: int = 5
    block_s: float = 2.0
    param_penalty: float = 0.25
    margin: float = 0.25
    min_gap_ratio: float = 2.0
    refit_top: int = 3
    refit_rounds: int = 2
    own_score: str = "cost"
    joint_refit: bool = False


def fold_masks(t: np.ndarray, opt: AttributionOptions) -> list:
    """K boolean (N,) masks of held-out samples: block b = floor((t − t0)/block_s) is in fold b mod K."""
    return held_out_masks(t, max(opt.block_s, 1e-9), opt.n_folds)


def _weighted(values: list, weights: list) -> float:
    w = np.asarray(weights, float)
    return float(np.sum(np.asarray(values, float) * w) / max(w.sum(), 1e-12))


def fold_gaps(real, sim, folds: list, gap_opt: GapOptions = GapOptions()) -> list:
    """Per fold: channel → (G1) of the base residuals on the held-out samples (None for empty folds)."""
    rate = real.session.rate
    return [gap(real.residuals, sim.residuals, real.sigma, rate, f, gap_opt, fits=(real, sim))
            if f.sum() >= 10 else None for f in folds]


# S17-H (docs/diagnose.md §S17-H, `DiagnoseOptions.fold_fixed_structure`, default on since session 17): an effect whose fit
# chooses a discrete structure (time_offset: which channel is late) is refitted in each fold with the structure
# of its all-sample fit held (`Effect.fit_fold`), so that every fold scores the model the verdict would name.
FOLD_FIXED_STRUCTURE = True
# S20-W (docs/diagnose.md §S20-W, `DiagnoseOptions.whitening_jacobian`, default off): the held-out log score (A4) of an
# effect whose residuals are WHITENED (linear_acceleration, vibration) adds its filter's Jacobian −(1/n) ln|det W|
# (nested.log_det (L3)), so that it is the log-likelihood of the raw residual, as the base model's is.
WHITENING_JACOBIAN = False


def fit_on_fold(effect, fitted, train: np.ndarray, window, full):
    """One fold's fit of `effect` on `train`: with the structure of its all-sample fit `full` held
    (`Effect.fit_fold`) under FOLD_FIXED_STRUCTURE, else a free `Effect.fit`."""
    if FOLD_FIXED_STRUCTURE and hasattr(effect, "fit_fold"):
        return effect.fit_fold(fitted, train, window, full)
    return effect.fit(fitted, train, window=window)



def null_gaps(null, sim, sigma: dict, folds: list, gap_opt: GapOptions = GapOptions()) -> dict:
    """channel → sample-weighted mean over the folds of (G1) of the independent simulation B against A
    (the noise floor at the size of these folds)."""
    rate = null.session.rate
    out = {c: 0.0 for c in CHANNELS}
    total = sum(float(f.sum()) for f in folds if f.sum() >= 10) or 1.0
    for f in folds:
        if f.sum() < 10:
            continue
        g = gap(null.residuals, sim.residuals, sigma, rate, f, gap_opt, fits=(null, sim))
        for c in CHANNELS:
            out[c] += g[c] * float(f.sum()) / total
    return out


def evaluate_effect(effect, real, sim, null_gap: dict, folds: list, opt: AttributionOptions,
                    gap_opt: GapOptions = GapOptions(), window=None, base: list | None = None,
                    ext=None, null=None) -> EffectResult:
    """Cross-validated gap before/after one effect ((A1), (A2)); the effect's parameters, window, channel
    (`Correction.channel`: time_offset and saturation choose theirs) and size are those of a final fit on
    all samples. base: `fold_gaps` (computed when not given). ext: the refitted extended model's θ* on
    the original measurements (imugraph.diagnose.refit); the effect is then fitted on it and the "after"
    residuals are rescaled by `refit.rescale`; None: the first-order fit on the base fit (screening).
    null: the fit of simulation B; with it, an effect that claims part of the recording (`effect_support`)
    is scored on the held-out samples of that part only, against the floor of the same samples (A3)."""
    from imugraph.diagnose.refit import rescale

    rate = real.session.rate
    fitted = real if ext is None else ext
    full = effect.fit(fitted, np.ones(real.n, bool), window=window)
    support = effect_support(full, real.session.t) if null is not None else None
    frac = 1.0
    scored = folds                                   # held-out samples scored (training: outside the fold)
    rest = None                                      # (A3): the recording's own gap outside the support
    if support is not None and scored_apart(support, rate):
        scored = [f & support for f in folds]                                                    # (A3)
        base = fold_gaps(real, sim, scored, gap_opt)
        null_gap = null_gaps(null, sim, real.sigma, scored, gap_opt)
        rest = null_gaps(real, sim, real.sigma, [f & ~support for f in folds], gap_opt)
        frac = float(support.mean())
    base = fold_gaps(real, sim, folds, gap_opt) if base is None else base
    before = {c: [] for c in CHANNELS}
    after = {c: [] for c in CHANNELS}
    weights = []
    fold_sizes = []
    ll = GainAccumulator()                                                                       # (A4)
    own, own_ll = OwnCostAccumulator(), OwnCostAccumulator()      # (J5), (J5'): the joint fit's own scores
    for fold, test, b in zip(folds, scored, base):
        if b is None:
            continue
        corr = fit_on_fold(effect, fitted, ~fold, window, full)           # S17-H (T11): the named model's structure
        if hasattr(effect, "size"):                                  # the size on this fold's training samples
            try:
                fold_sizes.append(float(effect.size(corr, fitted).get("value", np.nan)))
            except (KeyError, TypeError, ValueError, IndexError):
                fold_sizes.append(float("nan"))
        data = real if ext is None else ext
        raw = corr.raw_residuals(data)
        if WHITENING_JACOBIAN:             # S20-W (L3): a whitened residual's score charged its filter's ln|det W|
            from imugraph.diagnose.nested import log_det
        ll.add(real.residuals, raw, ~fold if support is None or rest is None else ~fold & support, test,
               j_ext=log_det(corr, data) if WHITENING_JACOBIAN else None)
        if (getattr(corr, "deltas", None) or {}).get("heldout") is not None:
            own.add_costs(corr.deltas["heldout"])
            own_ll.add_costs(corr.deltas["heldout"]["ll"])
        r_after = corr.residuals(real) if ext is None else rescale(raw, real, ~fold)
        a = gap({c: r_after.get(c, real.residuals[c]) for c in CHANNELS}, sim.residuals, real.sigma, rate,
                test, gap_opt, fits=(fitted, sim))                # (G1'): the trajectory of the residuals
        for c in CHANNELS:
            before[c].append(b[c])
            after[c].append(a[c])
        weights.append(test.sum())
    ch = getattr(full, "channel", "") or effect.channel
    n_params = int(getattr(full, "n_params", 0))
    bef = {c: _weighted(before[c], weights) for c in CHANNELS}
    aft = {c: _weighted(after[c], weights) for c in CHANNELS}
    noise = {c: float(null_gap.get(c, 0.0)) for c in CHANNELS}
    floor = dict(noise) if rest is None else {c: max(noise[c], float(rest[c])) for c in CHANNELS}   # (A3)
    g0, g1 = max(0.0, bef[ch] - floor[ch]), max(0.0, aft[ch] - floor[ch])
    shrink = 1.0 - g1 / g0 if g0 > 0 else 0.0                                                    # (A1)
    cost = opt.param_penalty * noise[ch] * np.log1p(max(n_params, 0))
    worse = sum(max(0.0, aft[c] - bef[c] - floor[c]) / max(bef[c] - floor[c], floor[c], 1e-12)
                for c in CHANNELS if c != ch)                  # a change within the noise floor is not worse
    penalised = (1.0 - (g1 + cost) / g0 if g0 > 0 else 0.0) - worse                              # (A2)
    size = effect.size(full, fitted) if hasattr(effect, "size") else {"value": np.inf, "threshold": 0.0}
    if hasattr(effect, "size_bound"):             # S20-V (T12): the relevance with the folds' uncertainty of the size
        size = effect.size_bound(size, fold_sizes)
    gain, gain_per, n_scored = ll.result(n_params)                                             # (A4')
    ll_base, ll_ext = ll.levels()
    own_gain, own_per, _ = own.result(n_params) if own.folds else (float("nan"), None, 0)
    own_ll_gain = own_ll.result(n_params)[0] if own_ll.folds else float("nan")
    gap_shrink, own_shrink = float(shrink), own.shrink(n_params)
    if opt.own_score == "cost" and own.folds:   # judged by (J5)/(J6): its shrink is (J6), like with like
        shrink = own_shrink
    return EffectResult(effect.name, ch, g0, g1, float(shrink), float(penalised), n_params,
                        full.t_start, full.t_end, dict(full.params), aft, bef[ch], size=size,
                        stage="screen" if ext is None else "refit", floor=noise[ch], support_fraction=frac,
                        decisive=bool((getattr(full, "deltas", None) or {}).get("decisive", False)),
                        loglik_gain=gain, loglik_per_channel=gain_per, n_scored=n_scored,
                        loglik_folds=ll.fold_gains(n_params), loglik_base=ll_base, loglik_ext=ll_ext,
                        own_gain=own_gain, own_per_channel=own_per,
                        own_folds=own.fold_gains(n_params) or None, own_ll_gain=own_ll_gain,
                        own_ll_folds=own_ll.fold_gains(n_params) or None,
                        own_shrink=own_shrink, gap_shrink=gap_shrink,
                        own_excess=own.excess() if own.folds else None, fold_sizes=fold_sizes or None)


def _failed(name, effect, exc) -> EffectResult:
    return EffectResult(name, getattr(effect, "channel", "?"), np.nan, np.nan, np.nan, -np.inf, 0,
                        error=f"{type(exc).__name__}: {exc} ({traceback.extract_tb(exc.__traceback__)[-1].name})")


def _line(res: EffectResult) -> str:
    s = res.size or {}
    return (f"effect {res.name} [{res.stage}]: gap {res.gap_before:.3f} → {res.gap_after:.3f}, shrink "
            f"{res.shrink:.2f}, penalised {res.penalised:.2f}, size {s.get('value', np.nan):.4g}/"
            f"{s.get('threshold', np.nan):.4g} {s.get('unit', '')}, log score {res.loglik_gain:+.4f} nats"
            + (f" [{res.error}]" if res.error else ""))


def candidates(results: list, null_gap: dict, n_top: int, effects: dict | None = None,
               opt: "AttributionOptions" = None) -> list:
    """Names of the effects to refit:

    * the `n_top` best screened effects that improved the held-out gap ((A2) > 0) and found something
      (size ≠ 0: a window, a rail, ...);
    * for every channel whose raw held-out gap is significant (≥ `min_gap_ratio` · null), the two best
      screened effects of that home channel (`Effect.channel`, or the channel the effect's own fit chose,
      `Correction.channel`: an accelerometer delay is time_offset on acc) whose screened size reaches half their
      relevance threshold — a distorted base fit hides an effect from the screening (negative (A2)) and
      makes its first-order size an underestimate, so the screening cannot be the judge there;
    * every effect whose own evidence is conclusive (`decisive`, saturation's rail (C2)): it can be the
      verdict whatever its screened score, so its reported shrink must be the extended model's (BROAD
      06/07 + clipped gyro: screened −0.28/−0.42, refitted 0.53 on 06).
    """
    opt = opt or AttributionOptions()
    ok = [r for r in results if np.isfinite(r.penalised) and (r.size or {}).get("value", 1.0) != 0.0]
    names = [r.name for r in ok if r.penalised > 0][:n_top]
    names += [r.name for r in ok if r.decisive and r.name not in names]      # can win on its own evidence
    for ch in CHANNELS:
        raw = next((r.raw_before for r in ok if r.channel == ch and np.isfinite(r.raw_before)), np.nan)
        if not raw >= opt.min_gap_ratio * null_gap.get(ch, 0.0):
            continue
        home = [r.name for r in ok if ch in (getattr((effects or {}).get(r.name), "channel", r.channel), r.channel)
                and (r.size or {}).get("value", np.inf) >= 0.5 * (r.size or {}).get("threshold", 0.0)][:2]
        names += [n for n in home if n not in names]
    return names


def attribute(real, sim, null_gap: dict, effects: dict, opt: AttributionOptions = AttributionOptions(),
              gap_opt: GapOptions = GapOptions(), windows: dict | None = None, progress=None,
              gap_excess: dict | None = None, null=None) -> list:
    """Screen every effect, refit the candidates; returns EffectResults best first (failed effects last,
    with `error`), `significant` set (`significant`).

    Args:
        real, sim: the real fit and the fit of a simulation from it (`fit.fit_simulation`).
        null_gap: channel → gap of an independent simulation against `sim` (noise floor).
        effects: name → Effect (imugraph.diagnose.effects.EFFECTS).
        windows: optional channel → (t_start, t_end) located by the gap curve, handed to windowed effects
            as a hint (they may refine it); None: each effect finds its own window.
        progress: optional callable(str) for progress lines.
        gap_excess: unused (kept for callers; the candidates come from the held-out gaps, `candidates`).
        null: the fit of simulation B (enables the support-restricted scoring (A3)); None: every effect
            is scored on the whole recording.
    """
    from imugraph.diagnose.refit import may_be_localised, refit_effect, refit_order, verdict_is_local

    say = progress or (lambda _m: None)
    folds = fold_masks(real.session.t, opt)
    base = fold_gaps(real, sim, folds, gap_opt)
    results = {}
    for name, effect in effects.items():                                   # stage 1: screening
        window = (windows or {}).get(effect.channel) if getattr(effect, "windowed", False) else None
        try:
            res = evaluate_effect(effect, real, sim, null_gap, folds, opt, gap_opt, window, base, null=null)
        except Exception as exc:   # one broken effect must not stop the diagnosis: reported, ranked last
            res = _failed(name, effect, exc)
        say(_line(res))
        results[name] = res
    ranked = _rank(list(results.values()))
    if opt.refit_top > 0 and opt.refit_rounds > 0:                         # stage 2: full refit
        refitted = []
        for name in refit_order(candidates(ranked, null_gap, opt.refit_top, effects, opt), results, effects):
            effect = effects[name]
            if not may_be_localised(effect, results[name]) and verdict_is_local(refitted, null_gap, opt):
                say(f"effect {name}: refit skipped (a localised effect is the verdict, (V))")
                continue
            if not opt.joint_refit and results[name].own_folds:
                say(f"effect {name}: refit skipped (fitted jointly with the trajectory: its screening stands)")
                continue
            window = (windows or {}).get(effect.channel) if getattr(effect, "windowed", False) else None
            try:
                refit = getattr(effect, "refit", None) or (lambda *a: refit_effect(effect, *a))
                ext, info = refit(real, opt.refit_rounds, window)      # the effect's own refit when it has one
                if not info["changed"]:
                    continue                                               # nothing to refit: screening stands
                res = evaluate_effect(effect, real, sim, null_gap, folds, opt, gap_opt, info["window"], base,
                                      ext=ext, null=null)
                res.refit = (ext, info)
                res.screen = {"shrink": results[name].shrink, "penalised_shrink": results[name].penalised,
                              "size": results[name].size}
            except Exception as exc:   # keep the screening result, say why the refit failed
                res = results[name]
                res.error = f"refit failed: {_failed(name, effect, exc).error}"
            say(_line(res))
            results[name] = res
            refitted.append(res)
    ranked = _rank(list(results.values()))
    for r in ranked:
        r.significant = significant(r, null_gap, opt)
    from imugraph.diagnose import local_check
    if local_check.LOCAL_CHECK:                                          # (V'), S17-H
        local_check.check_locals(ranked, real, folds, effects, say)
    from imugraph.diagnose import nested
    if nested.NESTED_CHECK:                                              # (V''), S20-W
        nested.check_nested(ranked, real, folds, effects, opt.margin, say)
    return ranked


def _rank(results: list) -> list:
    return sorted(results, key=lambda r: -r.penalised if np.isfinite(r.penalised) else np.inf)


def significant(res: EffectResult, null_gap: dict, opt: AttributionOptions = AttributionOptions()) -> bool:
    """Significance: on a channel whose raw gap is well above the noise floor (`min_gap_ratio` · null),
    the penalised held-out shrink (A2) clears `margin`; or, for an effect scored on its support (A3),
    the held-out log score (A4) on that support prefers the extended model, net of its BIC cost, overall
    and in every fold ((A4''), `score.clearly_better`; a proper scoring rule, which (G1) is not,
    docs/diagnose.md §3)."""
    if res.decisive:                  # conclusive evidence of its own (saturation's exact rail, (C2))
        return True
    if not np.isfinite(res.penalised):
        return False
    floor = res.floor if np.isfinite(res.floor) else null_gap.get(res.channel, 0.0)
    if not res.raw_before >= opt.min_gap_ratio * floor:
        return False
    if opt.own_score and res.own_folds:        # (J5)/(J5'): judged by the joint estimator's own scores
        if opt.own_score == "logscore":
            return clearly_better(res.own_ll_gain, res.own_ll_folds)
        return clearly_better(res.own_gain, res.own_folds) and bool(res.own_shrink >= opt.margin)   # (J6)
    by_score = res.support_fraction < 1.0 or (res.params or {}).get("significance") == "log_score"
    if by_score and clearly_better(res.loglik_gain, res.loglik_folds):
        return True          # (A4''): a localised effect preferred by the held-out log score on its support,
                             # or an effect whose fit asks for it (time_offset (T6), docs/diagnose.md §4 S14-A)
    return bool(res.penalised >= opt.margin)


LOCAL_FRACTION = 0.5        # an effect claiming less than this fraction of the recording is "localised"


def verdict(results: list, null_gap: dict, opt: AttributionOptions = AttributionOptions()) -> str:
    """The effect that is both significant (`significant`) and relevant (its fitted size reaches the
    effect's physical threshold, `EffectResult.relevant`); "none" when there is none. Among several, a
    localised one (scored by (A3) on its support: it explains what sets part of the recording apart from
    the rest of the same recording) comes first, then the best-ranked (A2) global one (V)."""
    ok = [r for r in results if significant(r, null_gap, opt) and r.relevant
          and not getattr(r, "explained_by", None)]                                                # (V')
    local = [r for r in ok if r.support_fraction < LOCAL_FRACTION]
    return (local or ok)[0].name if ok else NONE
