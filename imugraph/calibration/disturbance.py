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

Two verdicts (Options.window_trial_verdict): fit_offsets judges a window at the current orientations against
σ_mag; fit_offsets_on_trial models a window for one solve first and judges it on that solve (no cycling).
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
OUTLIER_K = 5.0           # fit_offsets_on_trial: rows of a modelled window with |r − Δo| > this × √3 × scale left out
TRIAL_GAIN = 0.5          # fit_offsets_on_trial: an offset is tried only if it leaves ≤ this × the window's RMS


@dataclass
class Window:
    """Samples [start, stop) of a disturbance; offset Δo_w (raw unit) when the window is modelled."""

    start: int
    stop: int
    offset: np.ndarray | None = None
    explained: bool = False
    residual_rms: float = float("nan")
    decided: bool = False      # `explained` fixed by an earlier fit (fit_offsets(keep_decision=True))
    on_trial: bool = False     # modelled for one solve, judged on it next (fit_offsets_on_trial)
    residual_scale: float = float("nan")   # robust per-axis scale of the residual after Δo_w (robust_scale)
    drop: np.ndarray | None = None         # sample indices of a modelled window left out (fit_offsets_on_trial)

    def as_dict(self, t: np.ndarray) -> dict:
        """The window as calibration.json carries it (Calibration.corrected applies it as apply_windows does):
        t_start/t_end (s, inclusive), offset, modelled, residual_rms, and left_out: [[t_a, t_b], ...] (s,
        inclusive), the runs of rows of a MODELLED window that the solve leaves out (w.drop; [] otherwise — an
        unmodelled window is left out whole by modelled = false)."""
        return {"t_start": float(t[self.start]), "t_end": float(t[self.stop - 1]),
                "offset": None if self.offset is None else np.asarray(self.offset).tolist(),
                "modelled": bool(self.explained), "residual_rms": float(self.residual_rms),
                "left_out": left_out_runs(t, self.drop) if self.explained and self.offset is not None else []}


def left_out_runs(t: np.ndarray, rows: np.ndarray | None) -> list[list[float]]:
    """Runs of consecutive row indices as [[t_first, t_last], ...] (s, inclusive); [] for None or no rows.
    Exact in JSON (floats round-trip), so t_first ≤ t ≤ t_last selects the same rows of the same session."""
    if rows is None or len(rows) == 0:
        return []
    idx = np.unique(np.asarray(rows, int))
    cut = np.flatnonzero(np.diff(idx) > 1)
    first, last = np.r_[idx[0], idx[cut + 1]], np.r_[idx[cut], idx[-1]]
    return [[float(t[a]), float(t[b])] for a, b in zip(first, last)]


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
        if _refit(w, t, b_mag, nRb, D, o, n_mag) is None:
            continue
        verdict = bool(w.residual_rms <= EXPLAINED * undisturbed_rms)
        w.explained = w.explained if keep_decision and w.decided else verdict
        w.decided = True


def field_residuals(b_mag: np.ndarray, nRb: np.ndarray, D: np.ndarray, o: np.ndarray,
                    n_mag: np.ndarray) -> np.ndarray:
    """r_j = y_j − (D bRn_j n_mag + o) for rows (M, 3) with their nRb (M, 3, 3), n_mag (3,) or (M, 3)."""
    n = np.broadcast_to(n_mag, (len(b_mag), 3))
    return b_mag - (np.einsum("ij,njk,nk->ni", D, np.transpose(nRb, (0, 2, 1)), n) + o)   # Kok's h(θ, R)


def _refit(w: Window, t, b_mag, nRb, D, o, n_mag, outliers: bool = False) -> float | None:
    """Δo_w = median_j r_j over the window and its residual RMS after it (w.offset, w.residual_rms); returns the
    RMS before the offset, or None (offset None, left out, decided) for a window too short or too sparse.
    outliers: also w.drop, the rows the offset does not explain, |r_j − Δo_w| > OUTLIER_K √3 s (5σ in 3-D)."""
    sl = slice(w.start, w.stop)
    y = b_mag[sl]
    ok = np.all(np.isfinite(y), axis=1)
    if ok.sum() < 10 or t[w.stop - 1] - t[w.start] < MIN_OFFSET_S:
        w.offset, w.explained, w.decided, w.on_trial = None, False, True, False
        return None
    n = n_mag if np.ndim(n_mag) == 1 else n_mag[sl][ok]          # (3,) or per sample (N, 3)
    r = field_residuals(y[ok], nRb[sl][ok], D, o, n)
    w.offset = np.median(r, axis=0)
    w.residual_rms = float(np.sqrt(np.mean((r - w.offset) ** 2)))
    w.residual_scale = robust_scale(r)
    if outliers:
        far = np.linalg.norm(r - w.offset, axis=1) > OUTLIER_K * np.sqrt(3.0) * w.residual_scale
        w.drop = w.start + np.flatnonzero(ok)[far]
    return float(np.sqrt(np.mean(r ** 2)))


def robust_scale(r: np.ndarray) -> float:
    """√(mean over axes of (1.4826 · MAD_axis)²) of residual rows r (M, 3): the RMS of Gaussian residuals, blind
    to a minority of outlying rows (a window's PAD_S margins, where the magnet is not yet there: ~58 µT off)."""
    mad = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    return float(np.sqrt(np.mean(mad ** 2)))


def fit_offsets_on_trial(windows: list[Window], t: np.ndarray, b_mag: np.ndarray, nRb: np.ndarray, D: np.ndarray,
                         o: np.ndarray, n_mag: np.ndarray, solve_rms) -> bool:
    """Δo_w for each window, each verdict judged on a solve WITH the window modelled, once (no cycling).

    A window's first fit runs at orientations solved without it (left out: heading from gyro + acc alone may
    drift, so its residual is no verdict). If its offset removes most of the residual there (RMS after ≤
    TRIAL_GAIN × before), it is modelled for the next solve ("on trial"); else it is left out for good (a
    nav-frame disturbance under rotation: D bRn Δn averages out in the body frame, simulated 25.0 → 24.8;
    tried anyway, the solve bent its orientations to fit the wrong offset, 9.7° RMS, and passed the test
    below). At the fit after the trial solve it is kept modelled for good when

        s_w(y − D bRn n − o − Δo_w) ≤ EXPLAINED · s_undisturbed(y − D bRn n − o)      (same solve)

    else left out for good; s is robust_scale (the window's padded margins hold the raw disturbance onset, a
    few % of its rows, which an RMS would count: 30 s simulated magnet, RMS 5.8 against its scale ≈ σ). The
    right side is the undisturbed samples' scale of that same solve (solve_rms(): called only when a window
    is judged), not σ_mag, which a left-out window leaks into.
    A modelled window leaves out its rows the offset does not explain (w.drop: the margins before the magnet
    arrives, 58 µT off on BROAD 32), fixed with the verdict. A decided window keeps its verdict and rows; its
    offset is refitted. Returns True when a window was put on trial
    (the rounds must not stop before it is judged).
    """
    pending, ref = False, None
    for w in windows:
        before = _refit(w, t, b_mag, nRb, D, o, n_mag, outliers=not w.decided)   # rows fixed once decided
        if before is None or w.decided:
            continue
        if w.on_trial:
            ref = solve_rms() if ref is None else ref
            w.explained, w.decided, w.on_trial = bool(w.residual_scale <= EXPLAINED * ref), True, False
        elif w.residual_rms <= TRIAL_GAIN * before:
            w.explained, w.on_trial, pending = True, True, True
        else:
            w.explained, w.decided = False, True
    return pending


def apply_windows(windows: list[Window], b_mag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The field with modelled offsets removed, and per-sample weights (0 inside unexplained windows)."""
    y = np.array(b_mag, float)
    weights = np.ones(len(y))
    for w in windows:
        if w.explained and w.offset is not None:
            y[w.start:w.stop] -= w.offset
            if w.drop is not None:
                weights[w.drop] = 0.0
        else:
            weights[w.start:w.stop] = 0.0
    return y, weights
