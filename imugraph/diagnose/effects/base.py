"""The effect interface of the diagnosis (docs/diagnose.md): inject an effect into a session, and extend the
fitted base model with the effect's parameters as a first-order refit.

First-order refit (every effect): the fitted trajectory x̂ (keyframe orientations) and the base parameters
stay fixed; the effect's few parameters are estimated by least squares on the training samples only (a
boolean mask), and `Correction.residuals` evaluates the extended model at every sample (the held-out ones
included). Three rules make the corrected residuals comparable with the simulated base residuals that the
gap (imugraph.diagnose.gap) compares them with:

1. Gyroscope effects change the measured rate by Δω_j = y'_j − y_j (y' = effect removed). With the
   keyframes fixed, the fit's per-sample orientation between keyframes s_k and s_{k+1} is the integrated
   gyro blended with the backward integration (imugraph.graphs.orientation_init.sample_orientations), so
   the refit trajectory moves by the small body-frame rotation

       δθ_j = φ_j − u_j Φ_k,   φ_j = Σ_{i=s_k}^{j−1} Δω_i Δt_i,   Φ_k = φ_{s_{k+1}},   u_j = (j−s_k)/(s_{k+1}−s_k)   (E1)

   and the residuals (R1)–(R3) of imugraph.diagnose.fit become, to first order in δθ,

       gyr'_j = gyr_j + Φ_k / T_k          (the keyframe mismatch rate c_k shrinks by Φ_k/T_k)         (E2)
       acc'_j = acc_j + δθ_j × (R̂_jᵀ(0,0,g)),     mag'_j = mag_j + D (δθ_j × R̂_jᵀ n_mag)                (E3)

2. Effects whose latent signal is local in time (linear acceleration, vibration) are given their
   hyper-parameters (spectrum) by the training samples and evaluated as standardised one-step residuals:
   the residual passed through the extended model's whitening filter (a fixed linear filter: it fits
   nothing to the held-out samples).
3. The extended model re-estimates the noise level of the channels it changes (as the ML loop of the
   calibration does): σ'_c from the training samples (Huber-weighted RMS, k = 2); corrected residuals
   are returned as r' · σ_c / σ'_c so that whitening by the base σ_c (what the gap does) gives the
   extended model's standardised residuals. Not the gyro: its σ is measured at rest and never
   re-estimated (base and extended model alike), so its residuals keep their size — the gap then sees
   how much of the gyro residual a correction removes, not only its shape.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.io.session import Session
from imugraph.io.validate import runs

CHANNELS = ("gyr", "acc", "mag")
EARTH_FIELD_UT = 50.0          # reference Earth field, µT: injected fields are given as µT-equivalents


@dataclass
class Correction:
    """The base model extended with one effect, fitted on training samples.

    Attributes:
        name: effect name (DESIGN.md). params: fitted parameters (JSON-ready). n_params: number of free
        parameters added to the model. t_start, t_end: the effect's main window, s (None: not windowed).
        channel: channel holding the evidence. deltas: private arrays the residuals need.
    """

    name: str
    params: dict
    n_params: int
    t_start: Optional[float] = None
    t_end: Optional[float] = None
    channel: str = ""
    deltas: dict = field(default_factory=dict, repr=False)

    def residuals(self, fit) -> dict:
        """channel → (N, 3) raw residuals of the extended model at every sample (module doc)."""
        out = self.raw_residuals(fit)
        for c, scale in self.deltas.get("noise_scale", {}).items():
            out[c] = out[c] * scale
        return out

    def raw_residuals(self, fit) -> dict:
        """Residuals before the noise re-estimation (rule 3). Subclasses override."""
        return {c: fit.residuals[c].copy() for c in CHANNELS}

    def corrected(self, fit) -> dict:
        """channel → measurements of `fit.session` with this effect removed (for the full refit,
        imugraph.diagnose.refit): the gyro changed by the correction's Δω when it has one (gyro effects),
        acc and mag by the change of their raw residual, y' = y + (r'_c − r_c) (R2)–(R3); NaN where the
        correction leaves no value (a censored sample keeps its measurement)."""
        s = fit.session
        out = {}
        if "d_omega" in self.deltas:
            out["gyr"] = s.gyr + np.nan_to_num(np.asarray(self.deltas["d_omega"], float))
        raw = self.raw_residuals(fit)
        for c in ("acc", "mag"):
            d = raw[c] - fit.residuals[c]
            if np.any(np.abs(np.nan_to_num(d)) > 0):
                y = getattr(s, c)
                out[c] = np.where(np.isfinite(d), y + np.nan_to_num(d), y)
        return out


class Effect:
    """One physical effect the base model leaves out (see module doc).

    Subclasses set `name`, `channel`, `windowed`, `ranges` (injection parameter ranges, documented) and
    implement `inject` and `fit`.
    """

    name: str = ""
    channel: str = ""
    windowed: bool = False
    ranges: dict = {}

    def inject(self, session: Session, rng: np.random.Generator, *, window=None, strength=None
               ) -> tuple[Session, dict]:
        """Add the effect to a session: (modified session, truth {"params", "t_start", "t_end"})."""
        raise NotImplementedError

    def fit(self, fit, train: np.ndarray, window=None) -> Correction:
        """Extend the base `fit` with this effect, estimated from the samples where `train` is True."""
        raise NotImplementedError

    def size(self, corr: Correction, fit) -> dict:
        """Relevance (docs/diagnose.md §3): the fitted effect's physical size {"value", "threshold",
        "unit"}; the effect can be the verdict only when value ≥ threshold. Subclasses override."""
        return {"value": float("inf"), "threshold": 0.0, "unit": ""}

    def __repr__(self) -> str:
        return f"<effect {self.name} ({self.channel}{', windowed' if self.windowed else ''})>"


# ---------------------------------------------------------------------------------------------- helpers
def check_train(fit, train) -> np.ndarray:
    """Validate the training mask: (N,) bool with enough samples."""
    train = np.asarray(train if train is not None else np.ones(fit.n, bool))
    if train.shape != (fit.n,) or train.dtype != bool:
        raise SessionError(fit.session.source, "train", f"shape {train.shape} dtype {train.dtype}",
                           f"a ({fit.n},) bool mask")
    if train.sum() < 10:
        raise SessionError(fit.session.source, "train", f"{int(train.sum())} samples", "≥ 10 training samples")
    return train


def replace_session(s: Session, *, t=None, gyr=None, acc=None, mag=None, name_suffix="", meta=None) -> Session:
    """A copy of `s` with some channels (or the stamps t) replaced (inputs untouched)."""
    m = dict(s.meta)
    m.update(meta or {})
    return Session(t=s.t.copy() if t is None else np.asarray(t, float),
                   gyr=s.gyr.copy() if gyr is None else np.asarray(gyr, float),
                   acc=s.acc.copy() if acc is None else np.asarray(acc, float),
                   mag=s.mag.copy() if mag is None else np.asarray(mag, float),
                   quat=None if s.quat is None else s.quat.copy(),
                   movement=None if s.movement is None else s.movement.copy(),
                   source=s.source, name=s.name + name_suffix, meta=m)


def field_scale(session: Session) -> float:
    """Earth-field magnitude in the session's magnetometer unit: median |b_mag − centre| with the centre
    the middle of each axis' range when the sensor turned enough (hard iron), else median |b_mag|."""
    y = session.mag[session.mag_valid]
    if len(y) == 0:
        return 1.0
    centre = 0.5 * (np.max(y, axis=0) + np.min(y, axis=0))
    spans = np.max(y, axis=0) - np.min(y, axis=0)
    r0 = float(np.median(np.linalg.norm(y, axis=1)))
    if np.all(spans > 1.2 * r0):                      # rotated over most of the sphere
        return float(np.median(np.linalg.norm(y - centre, axis=1)))
    return r0


def random_window(session: Session, rng: np.random.Generator, frac=(0.15, 0.4), margin_s=3.0
                  ) -> tuple[float, float]:
    """A random window (t_start, t_end) covering `frac` of the session, away from its ends."""
    t0, t1 = float(session.t[0]) + margin_s, float(session.t[-1]) - margin_s
    span = max(t1 - t0, 1e-6)
    length = rng.uniform(*frac) * span
    start = rng.uniform(t0, t1 - length)
    return float(start), float(start + length)


def envelope(t: np.ndarray, window: tuple[float, float], ramp_s: float) -> np.ndarray:
    """(N,) 0…1: raised-cosine ramps of `ramp_s` centred on the window's edges, 1 inside."""
    a, b = window
    r = max(ramp_s, 1e-9)
    up = np.clip((t - (a - r / 2)) / r, 0, 1)
    down = np.clip(((b + r / 2) - t) / r, 0, 1)
    return 0.5 * (1 - np.cos(np.pi * np.minimum(up, down)))


def huber_rms(r: np.ndarray, sigma: np.ndarray, k: float = 2.0) -> np.ndarray:
    """(3,) Huber-weighted RMS per axis of residuals r (M, 3) (NaN rows ignored), weights from |r/σ|."""
    r = r[np.all(np.isfinite(r), axis=1)]
    if len(r) < 3:
        return np.asarray(sigma, float)
    s = np.asarray(sigma, float).copy()
    for _ in range(3):
        z = np.linalg.norm(r / s, axis=1) / np.sqrt(3)
        w = np.where(z <= k, 1.0, k / np.maximum(z, 1e-12))
        s = np.sqrt(np.sum(w[:, None] * r**2, axis=0) / np.sum(w))
    return np.maximum(s, 1e-12)


def noise_scale(fit, res: dict, train: np.ndarray, channels) -> dict:
    """Rule 3: σ_c / σ'_c for the changed channels, σ'_c re-estimated on the training samples."""
    out = {}
    for c in channels:
        if c == "gyr":
            continue
        base = base_rms(fit, c, train)
        new = huber_rms(res[c][train], fit.sigma[c])
        out[c] = base / new
    return out


_BASE_RMS: dict = {}


def base_rms(fit, c: str, train: np.ndarray) -> np.ndarray:
    """huber_rms of the fit's own residuals of channel c on the training samples, cached per (fit, c,
    train): every effect's noise re-estimation on a fold divides by the same value (same numbers, once)."""
    import hashlib

    key = (id(fit), id(fit.residuals), c, hashlib.sha1(np.ascontiguousarray(train).tobytes()).hexdigest())
    hit = _BASE_RMS.get(key)
    if hit is None or hit[0] is not fit:
        if len(_BASE_RMS) >= 64:
            _BASE_RMS.pop(next(iter(_BASE_RMS)))
        hit = _BASE_RMS[key] = (fit, huber_rms(fit.residuals[c][train], fit.sigma[c]))
    return hit[1].copy()


def smooth(x: np.ndarray, n: int) -> np.ndarray:
    """NaN-aware centred moving average over n samples of (N,) or (N, d) x."""
    x = np.asarray(x, float)
    one = x.ndim == 1
    x2 = x[:, None] if one else x
    ok = np.isfinite(x2)
    n = max(1, int(n))
    ker = np.ones(n)
    num = np.stack([np.convolve(np.where(ok[:, i], x2[:, i], 0.0), ker, "same") for i in range(x2.shape[1])], 1)
    den = np.stack([np.convolve(ok[:, i].astype(float), ker, "same") for i in range(x2.shape[1])], 1)
    out = np.where(den > 0, num / np.maximum(den, 1e-12), np.nan)
    return out[:, 0] if one else out


def detect_windows(t: np.ndarray, score: np.ndarray, *, smooth_s: float = 1.0, factor: float = 4.0,
                   min_s: float = 2.0, merge_s: float = 1.5, quiet_q: float = 0.2) -> list:
    """Windows where a non-negative per-sample score (e.g. squared whitened residual) rises well above its
    quiet level: moving average over `smooth_s`, quiet level = its `quiet_q` quantile, flagged where above
    `factor` × quiet level; runs closer than `merge_s` merged, shorter than `min_s` dropped.

    Returns [(i_start, i_stop)] sample index ranges, longest first."""
    rate = 1.0 / float(np.median(np.diff(t)))
    s = smooth(score, int(round(smooth_s * rate)))
    fin = np.isfinite(s)
    if fin.sum() < 10:
        return []
    quiet = max(float(np.quantile(s[fin], quiet_q)), 1e-12)
    return flag_windows(t, np.where(fin, s > factor * quiet, False), merge_s, min_s)


def flag_windows(t: np.ndarray, flag: np.ndarray, merge_s: float, min_s: float) -> list:
    """[(i_start, i_stop)] of the runs of `flag`, runs closer than `merge_s` merged, shorter than `min_s`
    dropped, longest first."""
    a, b = runs(flag)
    merged = []
    for i0, i1 in zip(a, b):
        if merged and t[i0] - t[merged[-1][1] - 1] < merge_s:
            merged[-1] = (merged[-1][0], i1)
        else:
            merged.append((int(i0), int(i1)))
    out = [(i0, i1) for i0, i1 in merged if t[i1 - 1] - t[i0] >= min_s]
    return sorted(out, key=lambda w: -(w[1] - w[0]))


def refine_edge(x: np.ndarray, i: int, half: int) -> int:
    """Changepoint of the mean of x (N, d) within [i − half, i + half]: the split maximising the between-
    segment sum of squares (a step in the mean, e.g. a magnet put on or taken off)."""
    n = len(x)
    a, b = max(0, i - half), min(n, i + half)
    seg = x[a:b]
    ok = np.all(np.isfinite(seg), axis=1)
    seg = seg[ok]
    idx = np.flatnonzero(ok) + a
    m = len(seg)
    if m < 6:
        return i
    c = np.cumsum(seg, axis=0)
    total = c[-1]
    j = np.arange(2, m - 2)
    left = c[j - 1] / j[:, None]
    right = (total - c[j - 1]) / (m - j)[:, None]
    stat = (j * (m - j) / m) * np.sum((left - right) ** 2, axis=1)
    return int(idx[j[np.argmax(stat)]])


def window_mask(t: np.ndarray, windows) -> np.ndarray:
    """(N,) bool: samples inside any (t_start, t_end) window."""
    m = np.zeros(len(t), bool)
    for a, b in windows:
        m |= (t >= a) & (t <= b)
    return m


def injection_orientation(session: Session) -> np.ndarray:
    """(N, 3, 3) nRb to place nav-frame signals into the body frame when injecting: the truth `quat` where
    finite, else the gyro integrated from the first known orientation (good enough for a realistic
    direction of an injected nav-frame signal; its slow drift only rotates that signal)."""
    from imugraph.geometry import integrate_gyro, quat_to_rotmat

    q = None if session.quat is None else np.asarray(session.quat, float)
    if q is not None and np.all(np.isfinite(q)):
        return quat_to_rotmat(q)
    q0 = None
    if q is not None:
        ok = np.flatnonzero(np.all(np.isfinite(q), axis=1))
        q0 = q[ok[0]] if len(ok) else None
    return quat_to_rotmat(integrate_gyro(session.gyr, session.dt, q0))


def shift_signal(t: np.ndarray, y: np.ndarray, tau: float) -> np.ndarray:
    """y(t − τ) by linear interpolation per axis over the finite rows (ends held); NaN rows stay NaN.
    τ > 0 delays the signal."""
    out = np.full_like(y, np.nan)
    ok = np.all(np.isfinite(y), axis=1)
    if ok.sum() < 2:
        return y.copy()
    for a in range(y.shape[1]):
        out[ok, a] = np.interp(t[ok] - tau, t[ok], y[ok, a])
    return out


def psd_filter(x: np.ndarray, gain) -> np.ndarray:
    """Zero-phase filtering of the columns of x (N, d) by a real gain(f) given on np.fft.rfftfreq(N) (cycles
    per sample) as an (F,) or (F, d) array. NaN rows are filled with 0 for the filter and stay NaN."""
    ok = np.all(np.isfinite(x), axis=1)
    x0 = np.where(ok[:, None], x, 0.0)
    X = np.fft.rfft(x0, axis=0)
    g = np.asarray(gain, float)
    X = X * (g[:, None] if g.ndim == 1 else g)
    out = np.fft.irfft(X, n=len(x), axis=0)
    out[~ok] = np.nan
    return out


def train_psd(x: np.ndarray, mask: np.ndarray, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """Welch PSD (Hann, 50 % overlap) per column of x (N, d) over the segments lying entirely in `mask`
    (and finite). Returns (f in cycles/sample (F,), psd (F, d)); psd NaN when no segment fits."""
    ok = mask & np.all(np.isfinite(x), axis=1)
    win = np.hanning(nperseg)
    f = np.fft.rfftfreq(nperseg)
    acc = np.zeros((len(f), x.shape[1]))
    count = 0
    a, b = runs(ok)
    for i0, i1 in zip(a, b):
        for s in range(i0, i1 - nperseg + 1, nperseg // 2):
            seg = x[s:s + nperseg]
            seg = seg - seg.mean(axis=0)
            acc += np.abs(np.fft.rfft(seg * win[:, None], axis=0)) ** 2
            count += 1
    if count == 0:
        return f, np.full_like(acc, np.nan)
    return f, acc / count / np.sum(win**2)


# the gyro's effect on the fitted trajectory (keyframes fixed): imugraph/diagnose/effects/trajectory.py

def huber_weights(z: np.ndarray, k: float) -> np.ndarray:
    """(M,) weights √w of whitened rows z (M, 3): Huber with threshold k on ‖z‖/√3 (the calibration's kernel)."""
    a = np.linalg.norm(z, axis=1) / np.sqrt(3)
    return np.sqrt(np.minimum(1.0, k / np.maximum(a, 1e-12)))


from imugraph.diagnose.effects.trajectory import (_EXACT_CACHE, gyro_exact, gyro_refit,  # noqa: E402,F401
                                                  interval_index, interval_mean, reintegrate)
