"""Causal detection of lasting magnetometer disturbances in a stream (onset and end), for the online calibration.

The batch path (`imugraph.calibration.disturbance`) finds its windows over the whole recording from the norm of
the initially calibrated field, |D₀⁻¹(y − o₀)| − 1, and gives each a hard-iron offset or leaves its samples out.
A stream cannot look ahead; it sees one keyframe interval at a time. Here, per closed interval k (n_k valid
field samples), the same orientation-free quantity — the norm deviation of the field calibrated with the START
calibration — averaged over the interval and whitened:

    ē_k = mean_i (|D₀⁻¹(y_i − o₀)| − 1),     z_k = ē_k / σ_k,     σ_k² = σ_f² + σ_n² / n_k                (1)

σ_f: the field's own variation about the model: at least the nav-field perturbation's σ_d projected on the field
direction (n̂ᵀ diag(σ_d²) n̂ with n̂ = (cos δ, 0, −sin δ); 0.015 of the field with `calibration.ml`'s defaults), and
at least the robust RMS of ē_k over the LEARNING window (σ_f² ≥ median ē_k² / 0.4549, the χ²₁ median: robust to
disturbances in less than half of it) — the stream's first `learn_s` seconds, the bootstrap window that
the start calibration was fitted on (its own disturbance windows already removed from y), where no alarm is raised.
Why learned: indoors the norm deviation moves by more than σ_d between places (BROAD, undisturbed trials, start
calibration: −0.05 at the resting place, +0.02…+0.05 in motion, the same with the whole-trial calibration), so
σ_f = 0.015 alone raised alarms on every undisturbed trial; the start calibration's own error adds to it too
(BROAD 34: its bootstrap D is 13 % of the scale off the whole-trial batch's).
Floor: σ_f ≥ MIN_THRESHOLD / √κ with the batch's MIN_THRESHOLD (6 % of the field, `calibration.disturbance`: the
deviation that always counts as disturbed there), so that a sustained deviation below it never accumulates in the
CUSUM (its z² stays under the drift κ): BROAD 21 (undisturbed; the batch finds no window) held 4 learned σ
(≈ 0.065) for seconds and raised three alarms without the floor.
σ_n: one sample's noise along the field (σ_y / scale). Under "no disturbance" z_k² ~ χ²₁ (approximately: d_k is
correlated over τ_d = 1 s, so consecutive z_k are too; the thresholds below are per keyframe, and the CUSUM's
drift makes a run of moderate z_k count only when it is above that quantile on average). One-sided CUSUM
(Page 1954) on the χ² statistic:

    g_k = min(g_max, max(0, g_{k−1} + z_k² − κ)),   κ = χ²₁ quantile(1 − p_drift),   alarm while g_k > h,
    h = χ²₁ quantile(1 − p_alarm),   g_max = 2h                                                              (2)

Onset: the first keyframe of the excursion of g above 0 that raised the alarm (the CUSUM's change-point
estimate), widened by `pad_s` before it — those intervals are at most `max_lag_s` old when the alarm rises (the
calibration folds an interval in only once it has left the lag window, so flagging them still takes effect).
End: g back at 0 (≥ (g_max)/κ quiet keyframes, bounded: g is capped at g_max), the interval flagged `pad_s` beyond
the last keyframe whose z_k² exceeded κ. An alarm within `merge_s` of the previous window's end continues it (counted once).
Thresholds: chosen from χ² quantiles (p_alarm = 1e-4, p_drift = 0.01: κ = 6.63, h = 15.1 — a 4σ interval mean
alarms at once, a steady 3σ one after ≈ 7 keyframes), no per-trial tuning.

What is flagged is left out of the online calibration (`stream_online`: the refit's fold-in; with θ as a graph
state the keyframe's factor gives no information on θ, decided when its interval closes: no retro-flagging
there). The orientations keep their Huber magnetometer factor (as before) unless `StreamOptions.disturb_orient`.
"""

from __future__ import annotations

import math
from array import array

import numpy as np
from scipy.stats import chi2

from imugraph.calibration.disturbance import MERGE_S, MIN_THRESHOLD, PAD_S

__all__ = ["DisturbanceDetector", "field_norm_sigma"]

CHI2_1_MEDIAN = float(chi2.ppf(0.5, 1))      # 0.4549: median of z² under the null


def field_norm_sigma(field_sigma, dip_rad: float) -> float:
    """σ_f of (1): the nav-field perturbation's σ (per nav axis x along the horizontal field, y across, z up; a
    scalar: all three) projected on the field direction n̂ = (cos δ, 0, −sin δ); 0.015 when there is none."""
    if field_sigma is None:
        return 0.015
    s = np.broadcast_to(np.asarray(field_sigma, float), (3,))
    return float(math.hypot(math.cos(dip_rad) * s[0], math.sin(dip_rad) * s[2]))


class DisturbanceDetector:
    """The CUSUM (2) on the whitened interval means (1) of the field's norm deviation.

    Args:
        D0, o0: the start calibration (raw field → unit field: D₀⁻¹(y − o₀)).
        sigma_f: σ_f of (1) (field units); sigma_n: σ_n (one sample, field units).
        p_alarm, p_drift: the χ²₁ tail probabilities of h and κ in (2).
        pad_s, max_lag_s: widening of each window before its onset and after its end (s); how far back an onset
            may flag (s; the caller's lag: an interval older than that has already been used).
        learn_s: intervals starting before this (s since the first) only learn σ_f (robust RMS of ē_k); no alarm.
        merge_s: an alarm rising within this of the previous window's end continues that window (as the batch's
            MERGE_S: a body-fixed offset changes the norm with the orientation, so its z_k can dip for a moment).
        min_deviation: the floor's deviation (σ_f ≥ min_deviation / √κ); 0: no floor.
        learn_sigma: False: σ_f is not learned (the learning window only holds the alarms back): sigma_f and the floor.
    """

    def __init__(self, D0: np.ndarray, o0: np.ndarray, sigma_f: float, sigma_n: float, p_alarm: float = 1e-4,
                 p_drift: float = 0.01, pad_s: float = PAD_S, max_lag_s: float = 2.0, learn_s: float = 0.0,
                 merge_s: float = MERGE_S, min_deviation: float = MIN_THRESHOLD, learn_sigma: bool = True):
        self.D_inv = np.linalg.inv(np.asarray(D0, float))
        self.o = np.asarray(o0, float)
        self.kappa = float(chi2.ppf(1.0 - p_drift, 1))
        self.var_f = max(float(sigma_f) ** 2, min_deviation ** 2 / self.kappa)     # floor: see the module docstring
        self.var_n = float(sigma_n) ** 2
        self.h = float(chi2.ppf(1.0 - p_alarm, 1))
        self.g_max = 2.0 * self.h
        self.pad_s, self.max_lag_s, self.merge_s = float(pad_s), float(max_lag_s), float(merge_s)
        self.g = 0.0
        self.alarm = False
        self.t_rise = None          # start time of the current excursion of g above 0 (the change-point estimate)
        self.spans: list = []       # [onset, end] per window (s; end = last hot interval's end + pad_s, updated)
        self.learn_s, self.t0, self.learn_sigma = float(learn_s), None, bool(learn_sigma)
        self._learn = array("d")    # ē_k² over the learning window (8 bytes per keyframe; freed after it)

    def mean_deviation(self, y: np.ndarray) -> tuple[float, int]:
        """ē_k of (1) and n_k for one interval's raw field rows y (n, 3), NaN rows = no sample (ē NaN when n_k = 0)."""
        m = (np.asarray(y, float) - self.o) @ self.D_inv.T
        if not math.isfinite(float(m[:, 0].sum())):          # a row without a field (NaN): mask them
            m = m[np.isfinite(m[:, 0])]
        n = len(m)
        if n == 0:
            return float("nan"), 0
        return float(np.mean(np.sqrt(np.einsum("ij,ij->i", m, m))) - 1.0), n

    @property
    def windows(self) -> int:
        """Alarms raised that opened a window (a rise within merge_s of the last window continues it)."""
        return len(self.spans)

    @property
    def sigma_f(self) -> float:
        return math.sqrt(self.var_f)

    def step(self, t_start: float, t_end: float, y: np.ndarray) -> tuple[bool, float | None]:
        """Interval [t_start, t_end) closed with raw field rows y: (flag this interval, onset time from which the
        caller should flag earlier intervals too — set once, when an alarm rises; None otherwise).
        An interval without a field sample leaves the CUSUM as it is."""
        e, n = self.mean_deviation(y)
        if self.t0 is None:
            self.t0 = t_start
        if t_start - self.t0 < self.learn_s:          # the learning window: σ_f², no alarm
            if n and self.learn_sigma:
                self._learn.append(e * e)
            return False, None
        if len(self._learn):                           # end of learning: σ_f² ≥ median ē_k² / (χ²₁ median)
            self.var_f = max(self.var_f, float(np.median(self._learn)) / CHI2_1_MEDIAN)
            self._learn = array("d")
        z2 = e * e / (self.var_f + self.var_n / n) if n else None
        onset = None
        if z2 is not None:
            if self.g <= 0.0 and z2 > self.kappa:
                self.t_rise = t_start
            self.g = min(self.g_max, max(0.0, self.g + z2 - self.kappa))
            if not self.alarm and self.g > self.h:
                self.alarm = True
                rise = self.t_rise if self.t_rise is not None else t_start
                onset = max(rise - self.pad_s, t_end - self.max_lag_s)
                if self.spans and onset <= self.spans[-1][1] + self.merge_s:     # the previous window continues
                    onset = max(onset, self.spans[-1][1])
                else:
                    self.spans.append([onset, t_end + self.pad_s])
            if self.alarm and z2 > self.kappa:     # the window lasts at least to here (+ pad_s); a rising
                self.spans[-1][1] = t_end + self.pad_s   # alarm always has z² > κ (g went from ≤ h to > h)
            if self.alarm and self.g <= 0.0:
                self.alarm = False
        return bool(self.alarm or (self.spans and t_start <= self.spans[-1][1])), onset
