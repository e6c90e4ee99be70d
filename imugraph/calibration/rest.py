"""Rest detection and sensor noise levels from rest (the noise covariances of Kok et al. 2012).

The maximum-likelihood calibration weighs each sensor by its noise covariance Σ_ω, Σ_a, Σ_m (Kok,
Hol, Schön, Gustafsson, Luinge, FUSION 2012, weights of the ML cost); the paper takes them from a
stationary stretch of the recording. Here:

- `detect_rest` marks samples whose centred window (default 0.5 s) is calm: the gyroscope's window
  standard deviation (root of the summed per-axis variances) below `gyr_thresh`, the standard deviation
  of ‖acc‖ below `acc_thresh`, the window-mean angular rate below `gyr_mean_thresh` (so a smooth
  constant-rate turn is not "rest") and the window-mean ‖acc‖ within `acc_dev` of the median over the
  calm windows (gravity only). Window sums come from cumulative sums (no per-sample loop).
- `noise_from_rest` removes a straight line (mean and drift) from every contiguous rest segment and
  pools the residuals per axis (degrees of freedom n − 2 per segment): per-axis standard deviations of
  gyr (rad/s), acc (m/s²) and mag (raw unit, valid rows only), and the gyro bias (mean gyr at rest).

Fallback without rest (fewer than `MIN_REST` samples): white noise from second differences,
σ ≈ 1.4826·MAD(Δ²x)/√6 (Δ²x_k = x_{k+1} − 2x_k + x_{k−1} has noise variance 6σ², while a smooth
motion contributes only ≈ ẍ·dt²), and a zero gyro bias. The result says which method was used.
Every standard deviation is floored at `FLOOR` (quantised or held signals can give zero).
"""

from __future__ import annotations

import numpy as np

from imugraph.io.session import Session

MIN_REST = 20                                                 # samples of rest needed
FLOOR = {"gyr": 1e-5, "acc": 1e-4, "mag": 1e-6}               # rad/s, m/s², relative to median ‖mag‖


def moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving mean of (N, …) x over n samples (truncated at the ends), via cumulative sums."""
    N = x.shape[0]
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    idx = np.arange(N)
    lo = np.clip(idx - n // 2, 0, N)
    hi = np.clip(idx - n // 2 + n, 0, N)
    cnt = (hi - lo).reshape((N,) + (1,) * (x.ndim - 1))
    return (c[hi] - c[lo]) / cnt


def _moving_var(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving variance of (N, …) x (mean removed first for numerical stability)."""
    x = x - x.mean(axis=0)
    m = moving_mean(x, n)
    return np.maximum(moving_mean(x * x, n) - m * m, 0.0)


def detect_rest(session: Session, window_s: float = 0.5, gyr_thresh: float = 0.03,
                acc_thresh: float = 0.2, gyr_mean_thresh: float = 0.2,
                acc_dev: float = 0.3) -> np.ndarray:
    """Mark samples at rest.

    Args:
        session: the recording (gyr rad/s, acc m/s²).
        window_s: window length in s (centred on each sample).
        gyr_thresh: max window std of the gyro, rad/s (root of the summed per-axis variances).
        acc_thresh: max window std of ‖acc‖, m/s².
        gyr_mean_thresh: max window-mean ‖gyr‖, rad/s (above any plausible gyro bias).
        acc_dev: max |window-mean ‖acc‖ − median over calm windows|, m/s².

    Returns:
        (N,) bool, True at rest.
    """
    gyr, acc = np.asarray(session.gyr, float), np.asarray(session.acc, float)
    n = max(3, int(round(window_s * session.rate)))
    acc_norm = np.linalg.norm(acc, axis=1)
    gyr_std = np.sqrt(_moving_var(gyr, n).sum(axis=1))
    calm = ((gyr_std < gyr_thresh) & (np.sqrt(_moving_var(acc_norm, n)) < acc_thresh)
            & (np.linalg.norm(moving_mean(gyr, n), axis=1) < gyr_mean_thresh))
    calm &= np.isfinite(gyr_std)
    if not calm.any():
        return calm
    acc_mean = moving_mean(acc_norm, n)
    return calm & (np.abs(acc_mean - np.median(acc_mean[calm])) < acc_dev)


def _segments(mask: np.ndarray) -> np.ndarray:
    """(N,) bool → (N,) int label of the contiguous True run each sample is in (−1 outside)."""
    start = mask & ~np.concatenate([[False], mask[:-1]])
    return np.where(mask, np.cumsum(start) - 1, -1)


def _detrended_std(x: np.ndarray, t: np.ndarray, label: np.ndarray) -> np.ndarray | None:
    """Pooled per-axis std of (N, 3) x after removing a line a + b·t from each labelled segment.

    Segments with fewer than 3 samples are dropped. Returns None when nothing is left.
    """
    keep = label >= 0
    x, t, lab = x[keep], t[keep], label[keep]
    if lab.size == 0:
        return None
    _, lab = np.unique(lab, return_inverse=True)
    cnt = np.bincount(lab).astype(float)
    ok = cnt[lab] >= 3
    x, t, lab = x[ok], t[ok], lab[ok]
    if lab.size == 0:
        return None
    _, lab = np.unique(lab, return_inverse=True)
    cnt = np.bincount(lab).astype(float)
    tm = np.bincount(lab, t) / cnt
    tc = t - tm[lab]                                          # time centred per segment
    stt = np.bincount(lab, tc * tc)
    xm = np.stack([np.bincount(lab, x[:, i]) / cnt for i in range(3)], 1)
    slope = np.stack([np.bincount(lab, tc * x[:, i]) for i in range(3)], 1)
    slope /= np.where(stt > 0, stt, np.inf)[:, None]
    res = x - xm[lab] - slope[lab] * tc[:, None]
    dof = lab.size - 2 * cnt.size
    return np.sqrt(np.sum(res * res, axis=0) / max(dof, 1))


def _diff_std(x: np.ndarray) -> np.ndarray:
    """Per-axis white-noise std from second differences of the finite rows: 1.4826·MAD(Δ²x)/√6."""
    x = x[np.all(np.isfinite(x), axis=1)]
    if x.shape[0] < 4:
        return np.zeros(3)
    d = np.diff(x, n=2, axis=0)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(6.0)


def noise_from_rest(session: Session, rest_mask: np.ndarray) -> dict:
    """Per-axis noise standard deviations and gyro bias from the rest segments.

    Args:
        session: the recording.
        rest_mask: (N,) bool from `detect_rest`.

    Returns:
        dict with "gyr" (3,) rad/s, "acc" (3,) m/s², "mag" (3,) raw unit, "gyro_bias" (3,) rad/s,
        "method" ("rest" or "differences", per channel "mag_method" likewise) and "n_rest" (int).
    """
    rest = np.asarray(rest_mask, bool)
    t = np.asarray(session.t, float)
    label = _segments(rest)
    n_rest = int(rest.sum())
    out: dict = {"n_rest": n_rest}
    use_rest = n_rest >= MIN_REST
    for ch in ("gyr", "acc"):
        x = np.asarray(getattr(session, ch), float)
        s = _detrended_std(x, t, label) if use_rest else None
        out[ch] = np.maximum(s if s is not None else _diff_std(x), FLOOR[ch])
    out["method"] = "rest" if use_rest else "differences"
    mag = np.asarray(session.mag, float)
    valid = np.all(np.isfinite(mag), axis=1)
    mag_label = np.where(valid, label, -1)
    s = _detrended_std(mag, t, mag_label) if np.sum(mag_label >= 0) >= MIN_REST else None
    out["mag_method"] = "rest" if s is not None else "differences"
    scale = float(np.median(np.linalg.norm(mag[valid], axis=1))) if valid.any() else 1.0
    out["mag"] = np.maximum(s if s is not None else _diff_std(mag), FLOOR["mag"] * scale)
    gyr = np.asarray(session.gyr, float)
    out["gyro_bias"] = gyr[rest].mean(axis=0) if use_rest else np.zeros(3)
    return out
