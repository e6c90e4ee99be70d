"""What a fitted effect claims of the recording, and whether (A3) scores it apart (imugraph.diagnose.attribute,
module doc (A3)): its support, and the condition on the support's and its complement's sizes."""

from __future__ import annotations

import numpy as np

SUPPORT_PAD_S = 1.0        # a claimed window is scored with this margin (ramps, edge error)
MIN_SUPPORT_S = 4.0        # a support shorter than this (summed over the folds) is not scored apart


def effect_support(corr, t: np.ndarray) -> np.ndarray | None:
    """(N,) bool: the samples a fitted effect claims (module doc, (A3)), or None for a global effect.

    `Correction.deltas["support"]` when the effect sets it (saturation: its clipped runs), else the
    union of its `params["windows"]` widened by SUPPORT_PAD_S (magnetic_disturbance, vibration)."""
    sup = corr.deltas.get("support") if getattr(corr, "deltas", None) else None
    if sup is not None:
        return np.asarray(sup, bool)
    wins = (corr.params or {}).get("windows") if isinstance(corr.params, dict) else None
    if not wins:
        return None
    m = np.zeros(len(t), bool)
    for w in wins:
        m |= (t >= w["t_start"] - SUPPORT_PAD_S) & (t <= w["t_end"] + SUPPORT_PAD_S)
    return m


def scored_apart(support: np.ndarray, rate: float) -> bool:
    """(A3)'s condition: the support and its complement ≥ MIN_SUPPORT_S, the complement also ≥ 0.2·n."""
    min_n = MIN_SUPPORT_S * rate
    return bool(support.sum() >= min_n and (~support).sum() >= max(min_n, 0.2 * len(support)))
