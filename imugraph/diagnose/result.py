"""One effect's cross-validated result (imugraph.diagnose.attribute): the held-out gap before/after
(A1)–(A3), the held-out log score (A4)–(A4''), the effect's fitted size and the verdict flags. Written to
diagnosis.json `effects[]` by `EffectResult.as_dict`. (Moved out of attribute.py, which re-exports it.)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class EffectResult:
    """One effect's cross-validated result (definitions: the module doc of imugraph.diagnose.attribute)."""

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
    size: dict | None = None
    stage: str = "screen"
    screen: dict | None = None
    significant: bool = False
    refit: tuple | None = field(default=None, repr=False, compare=False)   # (θ*, info) of stage 2, reused
    floor: float = float("nan")           # noise floor of the channel on the samples scored (support)
    decisive: bool = False                # the effect's own evidence is conclusive (saturation (C2))
    support_fraction: float = 1.0         # fraction of the samples the effect claims (1: whole recording)
    loglik_gain: float = float("nan")     # (A4): held-out log-score gain, nats per sample, BIC cost charged
    loglik_per_channel: dict | None = None  # (A4) per channel, nats per sample (no cost)
    n_scored: int = 0                     # held-out samples scored (A4's BIC cost)
    loglik_folds: list | None = None      # (A4'') per fold, nats per sample, BIC cost charged
    loglik_base: dict | None = None       # (A4) ℓ of the base model per channel, nats per sample (held-out)
    loglik_ext: dict | None = None        # (A4) ℓ of the extended model per channel, nats per sample
    own_gain: float = float("nan")        # (J5): the joint estimator's own held-out cost gain, BIC charged
    own_per_channel: dict | None = None   # (J5) per channel, per sample (no cost)
    own_folds: list | None = None         # (J5) per fold, BIC cost charged (None: the fit reports none)
    own_ll_gain: float = float("nan")     # (J5'): (A4) of the two joint solutions, BIC cost charged
    own_ll_folds: list | None = None      # (J5') per fold
    own_shrink: float = float("nan")      # (J6): share of the base model's held-out excess cost removed
    gap_shrink: float = float("nan")      # (A1) always (`shrink` is (J6) for an effect judged by (J5)/(J6))
    own_excess: dict | None = None        # (J6) per channel: the base model's held-out cost per row − E0 (S17-H)
    fold_sizes: list | None = None        # the effect's size fitted on each fold's training samples (S17-H)
    explained_by: dict | None = None      # (V') S17-H: a global effect explains this localised one's support

    @property
    def relevant(self) -> bool:
        """The fitted effect's size reaches its physical threshold (docs/diagnose.md §3)."""
        s = self.size or {}
        return bool(s.get("value", np.nan) >= s.get("threshold", np.inf))     # NaN (no size) → False

    def as_dict(self) -> dict:
        return {"name": self.name, "channel": self.channel, "t_start": self.t_start, "t_end": self.t_end,
                "gap_before": self.gap_before, "gap_after": self.gap_after, "shrink": self.shrink,
                "penalised_shrink": self.penalised, "n_params": self.n_params,
                "params": self.params or {}, "gap_after_per_channel": self.per_channel_after or {},
                "size": self.size or {}, "relevant": self.relevant, "significant": self.significant,
                "stage": self.stage, "support_fraction": self.support_fraction, "decisive": self.decisive,
                "loglik_gain": self.loglik_gain, "loglik_gain_per_channel": self.loglik_per_channel or {},
                "loglik_gain_per_fold": self.loglik_folds or [], "size_per_fold": self.fold_sizes or [],
                "loglik_base_per_channel": self.loglik_base or {}, "loglik_ext_per_channel": self.loglik_ext or {},
                **({"own_cost_gain": self.own_gain, "own_cost_gain_per_channel": self.own_per_channel or {},
                    "own_cost_gain_per_fold": self.own_folds, "own_cost_shrink": self.own_shrink,
                    "gap_shrink": self.gap_shrink, "own_excess_per_channel": self.own_excess or {},
                    "own_loglik_gain": self.own_ll_gain,
                    "own_loglik_gain_per_fold": self.own_ll_folds or []} if self.own_folds else {}),
                **({"screen": self.screen} if self.screen else {}),
                **({"explained_by": self.explained_by} if self.explained_by else {}),
                **({"error": self.error} if self.error else {})}
