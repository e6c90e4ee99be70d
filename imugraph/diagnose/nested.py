"""(V'') S20-W: an effect named by the log-score route must beat the stronger effect on its channel, nested.

An effect E on channel c that is significant only through the held-out log score's sign test ((A4''):
time_offset (T6), or a localised effect (A3)) has been compared with the BARE base model. When another
relevant effect G on the same channel c predicts the held-out samples of c better (Δℓ(G) > Δℓ(E)), E's
gain may be a part of G's misfit that E's few parameters happen to absorb: a walking foot's linear
acceleration (5–8 m/s² RMS, impacts locked to the gait cycle, hence to the rotation) is partly "explained"
by shifting the accelerometer by 8 samples against the rotation (docs/diagnose.md §S20-W). The nested
test asks whether E is still preferred when fitted ON TOP OF G:

    per fold k (train ¬k, test k; E's all-sample structure held, `attribute.fit_on_fold`):
      Ĝ_k      = G.fit(θ̂, ¬k)                         r_G    = Ĝ_k.raw_residuals(θ̂)          (model G)
      Ê_k      = E.fit(θ̂, ¬k);  θ̂_E = θ̂ on the data with E removed (`Correction.corrected`, `refit.on_session`)
      Ĝ'_k     = G.fit(θ̂_E, ¬k)                       r_GE   = Ĝ'_k.raw_residuals(θ̂_E)       (model G + E)
      Δℓ(E | G) = (A4) of r_GE against r_G on fold k, minus E's BIC cost                      (V''1)

    (A4) of a FILTERED residual (linear_acceleration's whitening W, fitted per model) is a log-likelihood of
    the raw residual only with the filter's Jacobian −(1/n) ln|det W| added ((L3), `log_det`): two fits of G
    whiten by different filters, and without it the stronger filter wins whatever the data.

    E stays in the verdict only when Δℓ(E | G) passes (A4'') (> 0 overall and in every fold)      (V''2)

otherwise E is marked `explained_by` G and leaves the verdict (attribute.verdict), exactly as (V') does for a
localised effect. Nothing is tuned: the same proper score, the same sign test, the same folds; only the
reference model changes from "base" to "base + G" (a nested model comparison). An injected delay of a
channel that G does not explain keeps its gain on top of G. Module flag `NESTED_CHECK`
(DiagnoseOptions.nested_check), default off.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from imugraph.diagnose.score import GainAccumulator, clearly_better

NESTED_CHECK = False


def _mean_log_gain(g: np.ndarray, n: int) -> float:
    """(1/n) Σ over the n DFT bins of Σ_axis ln|H(f)|, H given on rfftfreq(n) as (F, 3) (each bin but DC and
    Nyquist counted twice: the filter is real, its spectrum symmetric)."""
    w = np.full(len(g), 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    return float(np.sum(w[:, None] * np.log(np.maximum(np.asarray(g, float), 1e-300))) / n)


def log_det(corr, fit) -> dict:
    """channel → (N,) per-sample share of ln|det W|, W the whitening filter a correction's residuals pass through
    (S20-W (L3)): linear_acceleration's |H| on every sample (`log_det_per_sample`), vibration's |H_w| inside
    each of its windows ((V1): √(S_out / (S_out + S_v,w))); {} for an effect whose residuals are the data
    minus a prediction (no Jacobian). The negative log-likelihood of the RAW residual is (A4) of the whitened
    one minus this (a filter with |H| ≤ 1 shrinks the residual, and is charged for it)."""
    n = fit.n
    fn = getattr(corr, "log_det_per_sample", None)
    if fn is not None:
        return {c: np.full(n, v) for c, v in fn(n, fit.session.rate).items()}
    d = getattr(corr, "deltas", None) or {}
    wins = (getattr(corr, "params", None) or {}).get("windows")
    if corr.name == "vibration" and wins and {"f", "s_out", "s_v"} <= set(d):
        from imugraph.diagnose.effects.base import window_mask

        out = np.zeros(n)
        for w, gain in corr.window_gains(n):                                    # (V1), as raw_residuals applies it
            out[window_mask(fit.session.t, [(w["t_start"], w["t_end"])])] = _mean_log_gain(gain, n)
        return {"acc": out}
    return {}


def by_log_score_only(res, margin: float) -> bool:
    """True when `res` is significant through (A4'') but not through (A2) (penalised < margin)."""
    route = res.support_fraction < 1.0 or (res.params or {}).get("significance") == "log_score"
    return bool(route and not (np.isfinite(res.penalised) and res.penalised >= margin) and not res.decisive)


def nested_gain(real, folds: list, res, other, effect, other_effect) -> dict | None:
    """Δℓ(E | G) of (V''1): `res`/`effect` = E, `other`/`other_effect` = G, both on the base fit θ̂ (the
    screening's first-order fits). Returns the gain (A4') and its per-fold values, or None without folds."""
    from imugraph.diagnose import attribute
    from imugraph.diagnose.effects.base import replace_session
    from imugraph.diagnose.refit import on_session

    full = SimpleNamespace(channel=res.channel)
    ll = GainAccumulator()
    for fold in folds:
        if fold.sum() < 10:
            continue
        train = ~fold
        g = other_effect.fit(real, train)                                             # model G
        corr_e = attribute.fit_on_fold(effect, real, train, None, full)              # E, structure held
        view = on_session(real, replace_session(real.session, **corr_e.corrected(real)))   # data without E
        ge = other_effect.fit(view, train)                                            # model G + E (V''1)
        j_ge = log_det(ge, view)                       # G's filter on the data without E, and E's own filter
        for c, j in log_det(corr_e, real).items():     # (vibration's whitening of its window) when it has one
            j_ge[c] = j_ge.get(c, 0.0) + j
        ll.add(g.raw_residuals(real), ge.raw_residuals(view), train, fold, log_det(g, real), j_ge)
    if not ll.folds:
        return None
    gain, per, _ = ll.result(res.n_params)
    return {"other": other.name, "channel": res.channel, "nested_gain": float(gain),
            "nested_folds": [float(x) for x in ll.fold_gains(res.n_params)],
            "own_gain": float(res.loglik_gain), "other_gain": float(other.loglik_gain)}


def check_nested(ranked: list, real, folds: list, effects: dict, margin: float, say=None) -> None:
    """(V''2): mark `explained_by` on each significant, relevant result named by the log-score route only
    that does not keep its gain on top of a relevant effect on its channel with a larger held-out log score."""
    say = say or (lambda _m: None)
    for r in ranked:
        if not (r.significant and r.relevant) or r.explained_by or not by_log_score_only(r, margin):
            continue
        stronger = [g for g in ranked if g is not r and g.channel == r.channel and g.relevant
                    and g.name in effects and r.name in effects and g.error is None
                    and np.isfinite(g.loglik_gain) and g.loglik_gain > r.loglik_gain]
        for g in stronger:
            try:
                chk = nested_gain(real, folds, r, g, effects[r.name], effects[g.name])
            except Exception as exc:        # a failed check leaves the verdict as (V) has it, said
                say(f"(V'') {r.name} on top of {g.name}: failed ({type(exc).__name__}: {exc})")
                continue
            if chk is None:
                continue
            ok = clearly_better(chk["nested_gain"], chk["nested_folds"])
            say(f"(V'') {r.name} on {r.channel} on top of {g.name}: {chk['nested_gain']:+.4f} nats per sample, "
                f"folds {', '.join(f'{x:+.3f}' for x in chk['nested_folds'])} → {'kept' if ok else 'explained'}")
            r.nested = chk
            if not ok:
                r.explained_by = {**chk, "rule": "nested (V'')"}
                break
