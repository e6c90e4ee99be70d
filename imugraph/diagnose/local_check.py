"""(V') S17-H: a localised verdict checked against a global effect that acts on the same channel.

The verdict rule (V) (attribute.verdict) puts a significant and relevant localised effect L before every
global one, because L explains what sets its support S apart from the rest of the recording, beyond the
misfit the two share — "which a global effect may explain as well". (V') asks whether one does: the held-out
log score (A4) of a significant and relevant global effect E on L's channel c, scored on the held-out samples
of S exactly as L is scored ((A3): E fitted on each fold's training samples — all of them, E is global —, both
models' σ from the training samples of S, test samples fold ∩ S):

    Δℓ_c(E; S) ≥ Δℓ_c(L; S)   →   L is not needed: E explains S at least as well; L leaves the verdict   (V')

Why: a channel delay makes the residual τ ḣ, largest where the motion is fastest, and (V2) can read such a
stretch as a vibration window (harness seed 3 case 007, BROAD 07 + 36 ms accelerometer delay: vibration
named, time_offset significant and relevant with every fold > 0). Nothing is tuned: both gains are the same
proper score on the same samples. Module flag `LOCAL_CHECK` (DiagnoseOptions.local_check), default off.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from imugraph.diagnose.score import GainAccumulator
from imugraph.diagnose.support import effect_support, scored_apart

LOCAL_CHECK = False


def global_gain_on_support(real, folds: list, local_res, global_res, effect) -> dict | None:
    """Δℓ_c of the global effect on the localised effect's support (module doc), or None when the support
    is unknown or when (A3) would not score it apart (S17-N1: the same condition as `evaluate_effect` —
    support and its complement ≥ MIN_SUPPORT_S, the complement also ≥ 0.2·n; otherwise L's own gain was not
    scored on S and the two gains would not be on the same samples)."""
    from imugraph.diagnose import attribute

    sup = effect_support(SimpleNamespace(deltas={}, params=local_res.params or {}), real.session.t)
    c = local_res.channel
    if sup is None or not local_res.loglik_per_channel or c not in local_res.loglik_per_channel:
        return None
    if not scored_apart(sup, real.session.rate):                         # (A3)'s condition
        return None
    # S17-N1: under T11 (attribute.FOLD_FIXED_STRUCTURE) the folds fit the model the verdict names — the
    # all-sample fit's channel held (`fit_fold`) —, so E is scored here as in its own evaluation
    full = SimpleNamespace(channel=global_res.channel)
    fitted = real if global_res.refit is None else global_res.refit[0]
    ll = GainAccumulator()
    for fold in folds:
        test = fold & sup
        if test.sum() < 10:
            continue
        corr = attribute.fit_on_fold(effect, fitted, ~fold, None, full)
        ll.add(real.residuals, corr.raw_residuals(fitted), ~fold & sup, test)
    if not ll.folds:
        return None
    _, per, _ = ll.result(global_res.n_params)
    return {"global": global_res.name, "channel": c, "global_gain": float(per.get(c, np.nan)),
            "local_gain": float(local_res.loglik_per_channel[c])}


def check_locals(ranked: list, real, folds: list, effects: dict, say=None) -> None:
    """(V'): mark `explained_by` on each significant, relevant localised result (in verdict order) that a
    significant, relevant global effect on its channel explains at least as well; stops at the first one
    that is not explained (the verdict's)."""
    from imugraph.diagnose.attribute import LOCAL_FRACTION

    say = say or (lambda _m: None)
    ok = [r for r in ranked if r.significant and r.relevant]
    glob = [r for r in ok if r.support_fraction >= LOCAL_FRACTION]
    for loc in [r for r in ok if r.support_fraction < LOCAL_FRACTION]:
        for g in glob:
            if g.channel != loc.channel or g.name not in effects:
                continue
            chk = global_gain_on_support(real, folds, loc, g, effects[g.name])
            if chk is None:
                continue
            say(f"(V') {loc.name} on {chk['channel']}: own gain {chk['local_gain']:+.4f}, {g.name} on its "
                f"support {chk['global_gain']:+.4f} nats per sample")
            if chk["global_gain"] >= chk["local_gain"]:
                loc.explained_by = chk
                break
        if loc.explained_by is None:
            return
