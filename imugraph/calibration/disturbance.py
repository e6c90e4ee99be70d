"""Magnetic disturbances that last: windows where the field leaves its calibrated sphere, and a
body-fixed hard-iron offset per window (a magnet or a ferrous tool attached to the sensor for a while).

Kok & Schön's model has one hard-iron offset o for the whole recording. A magnet attached to the sensor
for part of it adds a constant offset Δo_w in the sensor frame during that window only:

    b_mag,j = D·bRn,j·n_mag + o + Δo_w + e_j,      j ∈ window w                       (windowed hard iron)

A robust kernel cannot absorb this: the disturbed samples are many, not rare, and far off the sphere
(BROAD trial 32: 60 s of a 58 µT offset on a 44 µT field). The windows are found from the norm of the
initially calibrated field, |D₀⁻¹(y − o₀)| − 1, which stays within a few per cent while undisturbed.
Given the orientations, Δo_w is linear: the mean of y_j − D bRn_j n_mag − o over the window. When the
offset does not explain the window (a field disturbed in the navigation frame, e.g. a magnet lying on
the table, or a window with too little rotation to tell offset from heading), its samples are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_THRESHOLD = 0.06      # |norm − 1| that always counts as disturbed (6 % of the field)
SPREAD_FACTOR = 6.0       # ... or this many robust stds of the session's own norm deviation
SMOOTH_S = 0.5            # moving-median window for the norm deviation, s
MERGE_S = 1.0             # windows closer than this are merged, s
PAD_S = 0.5               # each window is widened by this on both sides, s
MIN_OFFSET_S = 3.0        # shorter windows are dropped, not given an offset
EXPLAINED = 3.0           # an offset explains its window when the residual RMS ≤ this × undisturbed RMS


@dataclass
class Window:
    """Samples [start, stop) of a disturbance; offset Δo_w (raw unit) when the window is modelled."""

    start: int
    stop: int
    offset: np.ndarray | None = None
    explained: bool = False
    residual_rms: float = float("nan")
    decided: bool = False      # `explained` fixed by an earlier fit (fit_offsets(keep_decision=True))

    def as_dict(self, t: np.ndarray) -> dict:
        return {"t_start": float(t[self.start]), "t_end": float(t[self.stop - 1]),
                "offset": None if self.offset is None else np.asarray(self.offset).tolist(),
                "modelled": bool(self.explained), "residual_rms": float(self.residual_rms)}


def _moving_median(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving median over n samples, edges padded with the end values (np.median of each
    window; for even n the mean of the two middle values), computed by scipy's rank filters."""
    if n <= 1 or len(x) < n:
        return x
    from scipy.ndimage import median_filter, rank_filter

    if n % 2:
        return median_filter(x, size=n, mode="nearest")
    return (rank_filter(x, n // 2 - 1, size=n, mode="nearest") + rank_filter(x, n // 2, size=n, mode="nearest")) / 2


def detect_windows(t: np.ndarray, m_cal: np.ndarray) -> list[Window]:
    """Disturbance windows from the initially calibrated field m_cal (N, 3), NaN rows = no sample."""
    valid = np.all(np.isfinite(m_cal), axis=1)
    if valid.sum() < 10:
        return []
    dev = np.full(len(t), 0.0)
    dev[valid] = np.abs(np.linalg.norm(m_cal[valid], axis=1) - 1.0)
    rate = 1.0 / float(np.median(np.diff(t)))
    dev_v = _moving_median(dev[valid], max(1, int(SMOOTH_S * rate * valid.mean())))
    sigma = 1.4826 * float(np.median(np.abs(dev_v - np.median(dev_v))))
    thr = max(MIN_THRESHOLD, float(np.median(dev_v)) + SPREAD_FACTOR * sigma)
    flag = np.zeros(len(t), bool)
    flag[np.flatnonzero(valid)[dev_v > thr]] = True
    if not flag.any():
        return []
    # runs of flagged samples, merged across short gaps and padded
    idx = np.flatnonzero(flag)
    gap = int(MERGE_S * rate)
    breaks = np.flatnonzero(np.diff(idx) > gap)
    starts = np.r_[idx[0], idx[breaks + 1]]
    stops = np.r_[idx[breaks], idx[-1]] + 1
    pad = int(PAD_S * rate)
    return [Window(max(0, int(a) - pad), min(len(t), int(b) + pad)) for a, b in zip(starts, stops)]


def fit_offsets(windows: list[Window], t: np.ndarray, b_mag: np.ndarray, nRb: np.ndarray, D: np.ndarray,
                o: np.ndarray, n_mag: np.ndarray, undisturbed_rms: float, keep_decision: bool = False) -> None:
    """Δo_w for each window given per-sample orientations nRb (N, 3, 3); marks whether it explains it.
    n_mag: the nav-frame field (3,), or per sample (N, 3) (with a field perturbation, imugraph.factors.field).
    keep_decision: a window's `explained` is decided at its first fit and kept (its offset is still refitted):
    the first fit sees orientations and a σ_mag the window did not influence (it starts left out); later
    verdicts depend on whether it was in the previous solve, and flipped on BROAD 32 (Options.freeze_window_decision).

    Δo_w = median_j (y_j − D bRn_j n_mag − o); explained when the remaining RMS (per axis) is within
    EXPLAINED × the undisturbed RMS and the window lasts at least MIN_OFFSET_S.
    """
    for w in windows:
        sl = slice(w.start, w.stop)
        y = b_mag[sl]
        ok = np.all(np.isfinite(y), axis=1)
        if ok.sum() < 10 or t[w.stop - 1] - t[w.start] < MIN_OFFSET_S:
            w.offset, w.explained = None, False
            continue
        n = n_mag if np.ndim(n_mag) == 1 else n_mag[sl][ok]          # (3,) or per sample (N, 3)
        pred = np.einsum("ij,njk,nk->ni", D, np.transpose(nRb[sl][ok], (0, 2, 1)),
                         np.broadcast_to(n, (int(ok.sum()), 3))) + o
        r = y[ok] - pred
        w.offset = np.median(r, axis=0)
        w.residual_rms = float(np.sqrt(np.mean((r - w.offset) ** 2)))
        verdict = bool(w.residual_rms <= EXPLAINED * undisturbed_rms)
        w.explained = w.explained if keep_decision and w.decided else verdict
        w.decided = True


def apply_windows(windows: list[Window], b_mag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The field with modelled offsets removed, and per-sample weights (0 inside unexplained windows)."""
    y = np.array(b_mag, float)
    weights = np.ones(len(y))
    for w in windows:
        if w.explained and w.offset is not None:
            y[w.start:w.stop] -= w.offset
        else:
            weights[w.start:w.stop] = 0.0
    return y, weights
