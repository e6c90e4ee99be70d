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
                "loglik_gain_per_fold": self.loglik_folds or [],
                "loglik_base_per_channel": self.loglik_base or {}, "loglik_ext_per_channel": self.loglik_ext or {},
                **({"screen": self.screen} if self.screen else {}),
                **({"error": self.error} if self.error else {})}
