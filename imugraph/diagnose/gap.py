"""The sim-to-real gap between the residuals of a real recording and of a simulation from its fitted model.

Both residual sets are whitened by the SAME σ (the real fit's, which the simulation was drawn with), so a
wrong noise level counts as well as a wrong shape or colour. For one channel, over a set of samples S:

    gap_c = (1/3) Σ_axis [ W1(F_real,axis, F_sim,axis) + w_ρ · (1/L) Σ_{l∈lags} |ρ_real,axis(l) − ρ_sim,axis(l)| ]   (G1)

    W1(F, G) = ∫₀¹ |F⁻¹(u) − G⁻¹(u)| du    (1-Wasserstein distance of the two empirical distributions,
                                           in whitened units; evaluated on a grid of 256 quantiles)   (G2)
    ρ(l) = Σ_i x̃_i x̃_{i+l} / Σ_i x̃_i²     (x̃ = x − mean over S; pairs with both samples in S)      (G3)

lags: log-spaced from one sample to `max_lag_s` (0.5 s). The first term sees bias, scale and shape
(heavy tails, outliers, bimodality); the second sees colour (slowly varying or oscillating errors) that
the model's white noise does not have. For data drawn from the model both terms are sampling noise,
→ 0 as S grows. Localisation evaluates (G1) in sliding windows (gap-vs-time curve per channel).

Cross-channel term (S16, opt-in: `GapOptions.cross_weight` > 0, default 0 = (G1) as above). (G1) looks at
each channel's marginal distribution and its own colour, so a channel that is consistent on its own but
not WITH the gyro — a delay, y_c(t) = h_c(t − τ) ≈ h_c(t) − τ ḣ_c — is nearly invisible there (S15 (c):
an 18 ms gyro delay adds 2 % to the acc gap of a hand-held crop). For acc and mag the model's prediction
h_c = R̂ᵀv (v fixed in the nav frame: gravity, the field) turns with the body, ḣ_c = h_c × ω̂ (ω̂ the
fitted body rate), and the term compares the correlation of each axis' whitened residual with it:

    x_c,axis = Σ_S z̃_axis ũ_axis / √(Σ_S z̃²_axis Σ_S ũ²_axis),   u = (h_c − o_c) × ω̂  (z̃, ũ centred on S)  (G4)
    gap_c += w_x · (1/3) Σ_axis |x_real,c,axis − x_sim,c,axis|                                        (G1')

    x'_c,axis = Σ_S z̃_axis ũ_axis / √(Σ_S ũ²_axis · |S|)       (cross_form="cov": not divided by std(z))  (G4')

For data from the model the residual is white noise independent of the motion, x ≈ 0 ± 1/√|S| (the
simulation's own x is subtracted: the fit's keyframes absorb a little of it alike). The gyro channel has
no such term (its residual is the keyframe mismatch rate, itself a cross-channel quantity). Applied to
the whole-recording and fold gaps (attribution), not to the localisation curve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imugraph.io.validate import runs

CHANNELS = ("gyr", "acc", "mag")


@dataclass(frozen=True)
class GapOptions:
    """Settings of the gap statistic and its localisation.

    Attributes:
        max_lag_s: longest autocorrelation lag of the whiteness term, s.
        n_lags: number of log-spaced lags (duplicates after rounding to samples are dropped).
        whiteness_weight: w_ρ in (G1).
        n_quantiles: quantile grid of (G2).
        window_s / hop_s: sliding window of the gap-vs-time curve, s.
        null_quantile: quantile of the simulation-vs-simulation curve above which a window is flagged.
        null_margin: factor on that quantile (the null curve is one draw: margin against its noise).
        spread_k: a window must also exceed median + k·1.4826·MAD of the recording's own curve (the gap
            is located where it is concentrated, not everywhere a misspecified model is off).
        min_duration_s: shortest location reported, s.
        cross_weight: w_x of the cross-channel term (G1') (S16; 0 = off, the default: (G1) alone).
        cross_form: "corr" (G4) or "cov" (G4'): the correlation, or the covariance in whitened units.
    """

    max_lag_s: float = 0.5
    n_lags: int = 8
    whiteness_weight: float = 1.0
    n_quantiles: int = 256
    window_s: float = 4.0
    hop_s: float = 1.0
    null_quantile: float = 0.99
    null_margin: float = 1.25
    spread_k: float = 3.0
    min_duration_s: float = 2.0
    cross_weight: float = 0.0
    cross_form: str = "corr"


def lag_grid(rate: float, opt: GapOptions) -> np.ndarray:
    """Integer lags (samples), log-spaced from 1 to max_lag_s·rate."""
    top = max(1, int(round(opt.max_lag_s * rate)))
    return np.unique(np.round(np.geomspace(1, top, opt.n_lags)).astype(int))


def wasserstein1(a: np.ndarray, b: np.ndarray, n_quantiles: int = 256) -> float:
    """(G2) 1-Wasserstein distance between the empirical distributions of 1-D samples a and b."""
    if a.size == 0 or b.size == 0:
        return 0.0
    u = (np.arange(n_quantiles) + 0.5) / n_quantiles
    return float(np.mean(np.abs(np.quantile(a, u) - np.quantile(b, u))))


def quantiles(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(len(u), d) quantiles of each column of x (n, d) at probabilities u: numpy's default "linear"
    method (F⁻¹(u) interpolated between the order statistics at u·(n−1)), from one sort of all columns
    instead of a partition per column and quantile (same values, several times faster)."""
    xs = np.sort(x, axis=0)
    n = xs.shape[0]
    idx = u * (n - 1)                                            # virtual index of F⁻¹(u)
    lo = np.floor(idx).astype(int)
    hi = np.minimum(lo + 1, n - 1)
    w = (idx - lo)[:, None]
    a, b = xs[lo], xs[hi]
    d = b - a
    return np.where(w >= 0.5, b - d * (1 - w), a + d * w)      # numpy's lerp, exact at both ends


def autocorrelation(x: np.ndarray, mask: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """(G3) normalised autocorrelation (len(lags), 3) of x (N, 3) over the samples in `mask` (pairs with
    both ends in the mask and finite). Zero where undefined."""
    ok = mask & np.all(np.isfinite(x), axis=1)
    out = np.zeros((len(lags), x.shape[1]))
    if ok.sum() < 3:
        return out
    xc = np.where(ok[:, None], x - np.nanmean(x[ok], axis=0), 0.0)
    var = np.sum(xc**2, axis=0) / ok.sum()
    var = np.where(var > 0, var, 1.0)
    okf = ok.astype(float)
    for i, lag in enumerate(lags):
        if lag >= len(x):
            break
        npair = float(np.dot(okf[:-lag], okf[lag:]))                 # pairs with both ends in S
        if npair > 0:
            out[i] = np.einsum("ij,ij->j", xc[:-lag], xc[lag:]) / npair / var
    return out


def motion_correlation(z: np.ndarray, u: np.ndarray, mask: np.ndarray, form: str = "corr") -> np.ndarray:
    """(G4) per-axis correlation (3,) of whitened residuals z (N, 3) with the model derivative u (N, 3)
    over the samples in mask where both are finite (zeros where undefined). form="cov": (G4'), the
    covariance with u scaled to unit std, in z's own (whitened) units — not divided by std(z), so a misfit
    independent of the motion (vibration, a hand's acceleration) neither dilutes it nor, once removed by a
    correction, raises it."""
    ok = mask & np.all(np.isfinite(z), axis=1) & np.all(np.isfinite(u), axis=1)
    if ok.sum() < 10:
        return np.zeros(z.shape[1])
    zc = z[ok] - z[ok].mean(axis=0)
    uc = u[ok] - u[ok].mean(axis=0)
    if form == "cov":                                                   # (G4') Σ z̃ũ / √(Σ ũ² · |S|)
        den = np.sqrt(np.sum(uc**2, axis=0) * ok.sum())
    else:
        den = np.sqrt(np.sum(zc**2, axis=0) * np.sum(uc**2, axis=0))
    return np.where(den > 0, np.sum(zc * uc, axis=0) / np.where(den > 0, den, 1.0), 0.0)


_DERIV_CACHE: dict = {}


def motion_derivatives(fit) -> dict:
    """channel → (N, 3) ḣ_c = (h_c − o_c) × ω̂ of a fitted base model (acc, mag; (G4)): the change of the
    body-frame prediction of a nav-fixed vector as the body turns. Cached per Fit object."""
    key = id(fit)
    hit = _DERIV_CACHE.get(key)
    if hit is not None and hit[0] is fit:
        return hit[1]
    pred = fit.predicted()
    w = fit.b_omega
    out = {"acc": np.cross(pred["acc"], w),
           "mag": np.cross(pred["mag"] - np.asarray(fit.calibration.o, float), w)}
    if len(_DERIV_CACHE) >= 32:
        _DERIV_CACHE.pop(next(iter(_DERIV_CACHE)))
    _DERIV_CACHE[key] = (fit, out)
    return out


def channel_gap(z_real: np.ndarray, z_sim: np.ndarray, mask: np.ndarray, lags: np.ndarray,
                opt: GapOptions = GapOptions(), parts: bool = False, u_real: np.ndarray | None = None,
                u_sim: np.ndarray | None = None):
    """(G1) gap of one channel between whitened residuals z_real, z_sim (N, 3) over the samples in mask;
    with opt.cross_weight > 0 and the model derivatives u_real, u_sim (N, 3) given, plus (G1').

    Returns the gap (float), or with parts=True the tuple (gap, distribution term, whiteness term)."""
    ok_r = mask & np.all(np.isfinite(z_real), axis=1)
    ok_s = mask & np.all(np.isfinite(z_sim), axis=1)
    if ok_r.sum() < 10 or ok_s.sum() < 10:
        return (0.0, 0.0, 0.0) if parts else 0.0
    u = (np.arange(opt.n_quantiles) + 0.5) / opt.n_quantiles
    q_sim, rho_sim = _sim_stats(z_sim, ok_s, mask, lags, u)
    dist = float(np.mean(np.mean(np.abs(quantiles(z_real[ok_r], u) - q_sim), axis=0)))              # (G2)
    rho = np.abs(autocorrelation(z_real, mask, lags) - rho_sim)
    white = float(np.mean(rho))
    g = float(dist + opt.whiteness_weight * white)
    if opt.cross_weight > 0 and u_real is not None and u_sim is not None:                       # (G1')
        g += opt.cross_weight * float(np.mean(np.abs(motion_correlation(z_real, u_real, mask, opt.cross_form)
                                                     - motion_correlation(z_sim, u_sim, mask, opt.cross_form))))
    return (g, float(dist), white) if parts else g


_SIM_CACHE: dict = {}


def _sim_stats(z_sim: np.ndarray, ok_s: np.ndarray, mask: np.ndarray, lags: np.ndarray, u: np.ndarray):
    """Quantiles (len(u), 3) and autocorrelation (G3) of the simulated side, cached by content: the
    attribution compares many corrected real residuals with the same simulated fold."""
    import hashlib

    h = hashlib.sha1()
    for a in (z_sim, mask, lags, u):
        h.update(np.ascontiguousarray(a).tobytes())
    key = h.hexdigest()
    if key not in _SIM_CACHE:
        if len(_SIM_CACHE) >= 64:
            _SIM_CACHE.pop(next(iter(_SIM_CACHE)))
        q = quantiles(z_sim[ok_s], u)
        _SIM_CACHE[key] = (q, autocorrelation(z_sim, mask, lags))
    return _SIM_CACHE[key]


def whiten(residuals: dict, sigma: dict) -> dict:
    """channel → residuals / σ (the real fit's σ for real, simulated and corrected residuals alike)."""
    return {c: residuals[c] / sigma[c] for c in CHANNELS if c in residuals}


def gap(real: dict, sim: dict, sigma: dict, rate: float, mask: np.ndarray | None = None,
        opt: GapOptions = GapOptions(), fits: tuple | None = None) -> dict:
    """channel → (G1) between raw residual dicts `real` and `sim` (N, 3 each), whitened by `sigma`,
    over the samples in `mask` (default all). fits: (fit of `real`'s trajectory, fit of `sim`) for the
    cross-channel term (G1') when opt.cross_weight > 0 (ignored otherwise)."""
    n = next(iter(real.values())).shape[0]
    mask = np.ones(n, bool) if mask is None else mask
    lags = lag_grid(rate, opt)
    zr, zs = whiten(real, sigma), whiten(sim, sigma)
    ur = us = {}
    if opt.cross_weight > 0 and fits is not None and fits[0] is not None and fits[1] is not None:
        ur, us = motion_derivatives(fits[0]), motion_derivatives(fits[1])
    return {c: channel_gap(zr[c], zs[c], mask, lags, opt, u_real=ur.get(c), u_sim=us.get(c))
            for c in CHANNELS if c in zr and c in zs}


@dataclass
class GapCurve:
    """Gap-vs-time per channel: window centres t (W,), channel → (W,) gap, and the flag threshold."""

    t: np.ndarray
    starts: np.ndarray
    stops: np.ndarray
    values: dict
    threshold: dict


def windows(t: np.ndarray, opt: GapOptions) -> tuple[np.ndarray, np.ndarray]:
    """Sample index ranges [start, stop) of the sliding windows."""
    t0, t1 = float(t[0]), float(t[-1])
    width = min(opt.window_s, t1 - t0)
    centres_t = np.arange(t0 + width / 2, t1 - width / 2 + 1e-9, opt.hop_s)
    starts = np.searchsorted(t, centres_t - width / 2)
    stops = np.searchsorted(t, centres_t + width / 2)
    return starts, stops


def gap_curve(real: dict, sim: dict, sigma: dict, t: np.ndarray, opt: GapOptions = GapOptions()) -> dict:
    """channel → (W,) gap (G1) in each sliding window (`windows`)."""
    rate = float(1.0 / np.median(np.diff(t)))
    lags = lag_grid(rate, GapOptions(max_lag_s=min(opt.max_lag_s, opt.window_s / 4), n_lags=opt.n_lags))
    zr, zs = whiten(real, sigma), whiten(sim, sigma)
    starts, stops = windows(t, opt)
    out = {}
    for c in CHANNELS:
        vals = np.zeros(len(starts))
        for i, (a, b) in enumerate(zip(starts, stops)):
            m = np.zeros(len(t), bool)
            m[a:b] = True
            vals[i] = channel_gap(zr[c][a:b], zs[c][a:b], m[a:b], lags, opt)
        out[c] = vals
    return out


def localise(t: np.ndarray, real_curve: dict, null_curve: dict, opt: GapOptions = GapOptions()):
    """Flag windows where the real curve exceeds both the null threshold (simulation vs simulation) and the
    recording's own spread; merge runs into locations.

    Returns:
        (GapCurve, locations): locations = [{"channel", "t_start", "t_end", "score"}], best score first;
        t_start/t_end span the centres of the flagged windows (score = mean real/threshold − 1 in the run).
    """
    starts, stops = windows(t, opt)
    centres = 0.5 * (t[starts] + t[np.maximum(stops - 1, starts)])
    thresholds, locations = {}, []
    for c in CHANNELS:
        thresholds[c], flagged = flag_runs(centres, real_curve[c], null_curve[c], opt)
        locations += [{"channel": c, "t_start": t0, "t_end": t1, "score": score} for t0, t1, score in flagged]
    locations.sort(key=lambda d: -d["score"])
    return GapCurve(centres, starts, stops, real_curve, thresholds), locations


def flag_runs(centres: np.ndarray, vals: np.ndarray, null: np.ndarray, opt: GapOptions) -> tuple[float, list]:
    """The threshold of a gap curve — above both the null curve's quantile (× null_margin) and the curve's
    own median + spread_k robust spreads — and its runs above it lasting ≥ min_duration_s, as
    [(t_start, t_end, score)] (centres of the first and last window; score = mean real/threshold − 1)."""
    mad = 1.4826 * np.median(np.abs(vals - np.median(vals))) if len(vals) else 0.0
    thr = max(opt.null_margin * float(np.quantile(null, opt.null_quantile)) if len(null) else 0.0,
              float(np.median(vals)) + opt.spread_k * mad if len(vals) else 0.0)
    flagged = []
    if len(vals):
        s, e = runs(vals > thr)
        for a, b in zip(s, e):
            t_start, t_end = float(centres[a]), float(centres[b - 1])
            if t_end - t_start + opt.hop_s >= opt.min_duration_s:
                flagged.append((t_start, t_end, float(np.mean(vals[a:b]) / max(thr, 1e-12) - 1.0)))
    return thr, flagged
