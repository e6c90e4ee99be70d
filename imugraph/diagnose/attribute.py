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
                   − Σ_{c ≠ c_E} max(0, after_c − before_c) / max(before_c − null_c, null_c)        (A2)

null_c is the gap of an independent simulation against the reference simulation at fold size (the
statistic's own sampling noise, its expected value when the data come from the model): gaps are reported
as the excess over it, so the gap of model data is ≈ 0 and a perfect correction shrinks it by 100 %.
Each parameter costs a fraction of the noise floor (BIC-like, logarithmic), and an effect that makes
another channel worse pays for it. Ranking is by (A2). The verdict is the best effect when its (A2) ≥
`margin` and its channel's raw gap is well above the noise floor (before_c ≥ `min_gap_ratio` · null_c);
otherwise "none".
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass

import numpy as np

from imugraph.diagnose.gap import CHANNELS, GapOptions, gap

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
    """

    n_folds: int = 5
    block_s: float = 2.0
    param_penalty: float = 0.5
    margin: float = 0.25
    min_gap_ratio: float = 5.0


def fold_masks(t: np.ndarray, opt: AttributionOptions) -> list:
    """K boolean (N,) masks of held-out samples: block b = floor((t − t0)/block_s) is in fold b mod K."""
    block = np.floor((t - t[0]) / max(opt.block_s, 1e-9)).astype(int)
    return [(block % opt.n_folds) == k for k in range(opt.n_folds)]


@dataclass
class EffectResult:
    """One effect's cross-validated result (see module doc)."""

    name: str
    channel: str
    gap_before: float
    gap_after: float
    shrink: float
    penalised: float
    n_params: int
    t_start: float | None = None
    t_end: float | None = None
    params: dict | None = None
    per_channel_after: dict | None = None
    raw_before: float = float("nan")
    error: str | None = None

    def as_dict(self) -> dict:
        return {"name": self.name, "channel": self.channel, "t_start": self.t_start, "t_end": self.t_end,
                "gap_before": self.gap_before, "gap_after": self.gap_after, "shrink": self.shrink,
                "penalised_shrink": self.penalised, "n_params": self.n_params,
                "params": self.params or {}, "gap_after_per_channel": self.per_channel_after or {},
                **({"error": self.error} if self.error else {})}


def _weighted(values: list, weights: list) -> float:
    w = np.asarray(weights, float)
    return float(np.sum(np.asarray(values, float) * w) / max(w.sum(), 1e-12))


def fold_gaps(real, sim, folds: list, gap_opt: GapOptions = GapOptions()) -> list:
    """Per fold: channel → (G1) of the base residuals on the held-out samples (None for empty folds)."""
    rate = real.session.rate
    return [gap(real.residuals, sim.residuals, real.sigma, rate, f, gap_opt) if f.sum() >= 10 else None
            for f in folds]


def evaluate_effect(effect, real, sim, null_gap: dict, folds: list, opt: AttributionOptions,
                    gap_opt: GapOptions = GapOptions(), window=None, base: list | None = None) -> EffectResult:
    """Cross-validated gap before/after one effect ((A1), (A2)); the effect's parameters and window are
    those of a final refit on all samples. base: `fold_gaps` (computed when not given)."""
    rate = real.session.rate
    base = fold_gaps(real, sim, folds, gap_opt) if base is None else base
    before = {c: [] for c in CHANNELS}
    after = {c: [] for c in CHANNELS}
    weights = []
    n_params = 0
    for test, b in zip(folds, base):
        if b is None:
            continue
        corr = effect.fit(real, ~test, window=window)
        n_params = int(corr.n_params)
        r_after = corr.residuals(real)
        a = gap({c: r_after.get(c, real.residuals[c]) for c in CHANNELS}, sim.residuals, real.sigma, rate,
                test, gap_opt)
        for c in CHANNELS:
            before[c].append(b[c])
            after[c].append(a[c])
        weights.append(test.sum())
    ch = effect.channel
    bef = {c: _weighted(before[c], weights) for c in CHANNELS}
    aft = {c: _weighted(after[c], weights) for c in CHANNELS}
    floor = {c: float(null_gap.get(c, 0.0)) for c in CHANNELS}
    g0, g1 = max(0.0, bef[ch] - floor[ch]), max(0.0, aft[ch] - floor[ch])
    shrink = 1.0 - g1 / g0 if g0 > 0 else 0.0                                                    # (A1)
    cost = opt.param_penalty * floor[ch] * np.log1p(max(n_params, 0))
    worse = sum(max(0.0, aft[c] - bef[c]) / max(bef[c] - floor[c], floor[c], 1e-12)
                for c in CHANNELS if c != ch)
    penalised = (1.0 - (g1 + cost) / g0 if g0 > 0 else 0.0) - worse                              # (A2)
    full = effect.fit(real, np.ones(real.n, bool), window=window)
    return EffectResult(effect.name, ch, g0, g1, float(shrink), float(penalised), int(full.n_params),
                        full.t_start, full.t_end, dict(full.params), aft, bef[ch])


def attribute(real, sim, null_gap: dict, effects: dict, opt: AttributionOptions = AttributionOptions(),
              gap_opt: GapOptions = GapOptions(), windows: dict | None = None, progress=None) -> list:
    """Evaluate every effect; returns EffectResults best first (failed effects last, with `error`).

    Args:
        real, sim: the real fit and the fit of a simulation from it (`fit.fit_simulation`).
        null_gap: channel → gap of an independent simulation against `sim` (noise floor).
        effects: name → Effect (imugraph.diagnose.effects.EFFECTS).
        windows: optional channel → (t_start, t_end) located by the gap curve, handed to windowed effects
            as a hint (they may refine it); None: each effect finds its own window.
        progress: optional callable(str) for progress lines.
    """
    folds = fold_masks(real.session.t, opt)
    base = fold_gaps(real, sim, folds, gap_opt)
    results = []
    for name, effect in effects.items():
        window = (windows or {}).get(effect.channel) if getattr(effect, "windowed", False) else None
        try:
            res = evaluate_effect(effect, real, sim, null_gap, folds, opt, gap_opt, window, base)
        except Exception as exc:   # one broken effect must not stop the diagnosis: reported, ranked last
            res = EffectResult(name, getattr(effect, "channel", "?"), np.nan, np.nan, np.nan, -np.inf, 0,
                               error=f"{type(exc).__name__}: {exc} "
                                     f"({traceback.extract_tb(exc.__traceback__)[-1].name})")
        if progress:
            progress(f"effect {name}: gap {res.gap_before:.3f} → {res.gap_after:.3f}, shrink {res.shrink:.2f}, penalised {res.penalised:.2f}"
                     + (f" [{res.error}]" if res.error else ""))
        results.append(res)
    results.sort(key=lambda r: -r.penalised if np.isfinite(r.penalised) else np.inf)
    return results


def verdict(results: list, null_gap: dict, opt: AttributionOptions = AttributionOptions()) -> str:
    """The best effect's name when it beats the base model by the margin on a channel whose gap is above
    the noise floor, else "none"."""
    if not results or not np.isfinite(results[0].penalised):
        return NONE
    best = results[0]
    floor = opt.min_gap_ratio * null_gap.get(best.channel, 0.0)
    if best.penalised >= opt.margin and best.raw_before >= floor:
        return best.name
    return NONE
