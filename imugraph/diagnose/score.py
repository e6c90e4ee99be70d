"""The held-out log score (A4): a proper scoring rule for the attribution (docs/diagnose.md §3).

Each model m (the base model, or the base model extended by an effect) predicts the residual of channel c
as zero-mean Gaussian noise with its OWN per-axis σ, estimated on the training samples of the fold:

    s²_m,a = mean_{i ∈ train} r²_m,i,a                                   (ML noise level, out of sample)
    ℓ_m   = mean_{i ∈ test} Σ_axis [ ½ (r_m,i,a / s_m,a)² + ln s_m,a ]    (negative log predictive
                                                                         density, nats, + ½ ln 2π)   (A4)

The gain of the effect on channel c is Δℓ_c = ℓ_base − ℓ_ext (> 0: the extended model predicts the
held-out samples better), averaged over the folds (sample-weighted). Its sum over the channels, minus a
BIC cost of the parameters the effect adds,

    G = Σ_c Δℓ_c − k ln(N) / (2N)          (k = n_params, N = held-out samples scored)             (A4')

is the held-out log-likelihood ratio per sample. The log score is strictly proper: its expectation is
smallest for the true predictive distribution, so an extended model that removes a real effect cannot
lower G in expectation — unlike (G1), which compares the SHAPE and COLOUR of the whitened residuals with
the simulation's after the noise re-estimation and can rise when a real effect is removed (the rest of
the misfit, rescaled to the old σ, then dominates the shape). A correction that makes another channel
worse pays for it in the sum, with no extra rule. Rows where either model has no value (NaN: a censored
or missing sample) are left out of both.
"""

from __future__ import annotations

import numpy as np

CHANNELS = ("gyr", "acc", "mag")


def _axis_sigma(r: np.ndarray, train: np.ndarray) -> np.ndarray:
    """Per-axis ML σ of residuals r (N, 3) on the rows `train` (floored to avoid ln 0)."""
    x = r[train]
    s = np.sqrt(np.mean(x * x, axis=0)) if len(x) else np.ones(r.shape[1])
    return np.maximum(np.nan_to_num(s, nan=1.0), 1e-12)


def log_score_sum(r: np.ndarray, train: np.ndarray, test: np.ndarray) -> float:
    """Σ over the rows `test` of (A4)'s per-sample score of residuals r, σ from the rows `train`."""
    s = _axis_sigma(r, train)
    z = r[test] / s
    return float(np.sum(0.5 * z * z) + test.sum() * np.sum(np.log(s)))


def channel_scores(r_base: np.ndarray, r_ext: np.ndarray, train: np.ndarray, test: np.ndarray) -> tuple:
    """(Σ_test ℓ_base, Σ_test ℓ_ext, n_test) on one channel: rows finite in both models only."""
    ok = np.all(np.isfinite(r_base), axis=1) & np.all(np.isfinite(r_ext), axis=1)
    tr, te = train & ok, test & ok
    if tr.sum() < 10 or te.sum() == 0:
        return 0.0, 0.0, 0
    return log_score_sum(r_base, tr, te), log_score_sum(r_ext, tr, te), int(te.sum())


def channel_gain(r_base: np.ndarray, r_ext: np.ndarray, train: np.ndarray, test: np.ndarray) -> tuple:
    """(Σ_test (ℓ_base − ℓ_ext), n_test) on one channel: rows finite in both models only."""
    lb, le, n = channel_scores(r_base, r_ext, train, test)
    return lb - le, n


class GainAccumulator:
    """Sums (A4) over the folds of one effect; `result(n_params)` gives (G (A4'), per-channel Δℓ_c, N)."""

    def __init__(self):
        self.sum = {c: 0.0 for c in CHANNELS}
        self.n = {c: 0 for c in CHANNELS}
        self.folds = []                     # per fold: Σ_c Δℓ_c of that fold alone (nats per sample)
        self.base = {c: 0.0 for c in CHANNELS}       # Σ ℓ_base, Σ ℓ_ext (absolute levels, `levels`)
        self.ext = {c: 0.0 for c in CHANNELS}

    def add(self, base: dict, ext: dict, train: np.ndarray, test: np.ndarray, j_base: dict | None = None,
            j_ext: dict | None = None) -> None:
        """Add one fold: base/ext are channel → (N, 3) raw residuals (ext falls back to base). j_base/j_ext:
        channel → (N,) per-sample ln|det W| of a model whose residuals are whitened (S20-W (L3), `nested.log_det`),
        charged on the scored rows: ℓ_m − Σ_test J_m (rows finite in both models)."""
        scores = {}
        for c in CHANNELS:
            if c not in base:
                continue
            rb, re = np.asarray(base[c], float), np.asarray(ext.get(c, base[c]), float)
            lb, le, n = channel_scores(rb, re, train, test)
            jb, je = (j_base or {}).get(c), (j_ext or {}).get(c)
            if n and (jb is not None or je is not None):
                ok = test & np.all(np.isfinite(rb), axis=1) & np.all(np.isfinite(re), axis=1)
                lb -= float(np.sum(jb[ok])) if jb is not None else 0.0
                le -= float(np.sum(je[ok])) if je is not None else 0.0
            scores[c] = (lb, le, n)
        self._add_fold(scores)

    def _add_fold(self, scores: dict) -> None:
        """One fold's channel → (ℓ_base, ℓ_ext, rows) summed in; its Σ_c Δℓ_c / rows kept per fold."""
        fold = 0.0
        for c in CHANNELS:
            if c not in scores:
                continue
            lb, le, n = scores[c]
            g = lb - le
            self.sum[c] += g
            self.base[c] += lb
            self.ext[c] += le
            self.n[c] += n
            fold += g / n if n else 0.0
        self.folds.append(fold)

    def result(self, n_params: int) -> tuple:
        per = {c: (self.sum[c] / self.n[c] if self.n[c] else 0.0) for c in CHANNELS}
        n = max(self.n.values()) if self.n else 0
        cost = max(n_params, 0) * np.log(max(n, 2)) / (2.0 * max(n, 1))               # BIC (A4')
        return float(sum(per.values()) - cost), per, n

    def levels(self) -> tuple:
        """(channel → ℓ_base, channel → ℓ_ext): the held-out scores (A4) themselves, nats per sample
        (sample-weighted over the folds; without the constant ½ ln 2π per axis). Their difference is Δℓ_c;
        the level lets a caller compare the base model's score on two recordings of the same samples
        (the harness: an injected case and its clean host, `harness.injected_part_logscore_shrink`)."""
        return ({c: (self.base[c] / self.n[c] if self.n[c] else float("nan")) for c in CHANNELS},
                {c: (self.ext[c] / self.n[c] if self.n[c] else float("nan")) for c in CHANNELS})

    def fold_gains(self, n_params: int) -> list:
        """Per fold: that fold's Σ_c Δℓ_c net of the same BIC cost as `result` (A4'')."""
        n = max(self.n.values()) if self.n else 0
        cost = max(n_params, 0) * np.log(max(n, 2)) / (2.0 * max(n, 1))
        return [float(f - cost) for f in self.folds]


def clearly_better(gain: float, folds) -> bool:
    """(A4''): the extended model is preferred by the held-out log score with a clear margin: its gain
    net of the BIC cost is positive overall AND in every fold — a sign test over the K folds (K = 5:
    probability 2⁻⁵ ≈ 0.03 that all five are positive when the effect adds nothing and a fold's gain is
    as likely negative as positive). The fold-to-fold spread carries the residuals' colour, which the
    BIC cost (independent samples) does not."""
    folds = list(folds or [])
    return bool(np.isfinite(gain) and gain > 0.0 and len(folds) >= 2 and all(f > 0.0 for f in folds))


class OwnCostAccumulator(GainAccumulator):
    """Sums an estimator's OWN held-out cost over the folds (effects/joint.py (J5): the Huber cost (J1)
    of the held-out rows under the base and the extended model, both solved the same way). Its gain per
    channel is (C_base − C_ext) / rows, nats per sample when the cost is a negative log-likelihood (J1:
    ½‖z‖² inside the Huber kernel); `result`, `fold_gains`, `levels` as GainAccumulator's, so the sign
    test (A4'') applies unchanged."""

    def __init__(self):
        super().__init__()
        self.e0 = {}                        # channel → the model noise's own cost per row (joint.heldout_cost)

    def add_costs(self, held: dict) -> None:
        """Add one fold: held = {"base": {c: C}, "ext": {c: C}, "n": {c: rows}} (joint.heldout_cost)."""
        for c, e in (held.get("e0") or {}).items():
            self.e0[c] = float(e)
        self._add_fold({c: (float(held["base"][c]), float(held["ext"][c]), int(held["n"][c]))
                        for c in CHANNELS if int(held["n"].get(c, 0))})

    def excess(self) -> dict:
        """channel → the base model's held-out cost per row − E0 (J6's denominator before max(0, ·))."""
        return {c: self.base[c] / self.n[c] - self.e0.get(c, 0.0) for c in CHANNELS if self.n[c]}

    def shrink(self, n_params: int) -> float:
        """The fraction of the base model's held-out EXCESS cost that the effect removes, net of the BIC
        cost (J6) — (A2)'s "share of the channel's gap" in the estimator's own objective:

            S = (Σ_c ΔC_c − k ln N / (2N)) / Σ_c max(0, C_base,c − E0_c)       (per row; E0: `e0`)

        NaN when no fold was added or the base model has no excess."""
        if not self.folds:
            return float("nan")
        gain, per, n = self.result(n_params)
        excess = sum(max(0.0, e) for e in self.excess().values())
        return float(gain / excess) if excess > 0 else float("nan")
