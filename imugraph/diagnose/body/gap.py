"""The sim-to-real gap of a body session per sensor × channel, and its localisation (docs/diagnose_body.md §2–3).

For sensor s and channel c (gyr, acc, pos, joint per keyframe interval, jacc per sample: imugraph.diagnose.body.fit
(BR1)–(BR4)) the residual series
of the real fit, of simulation A and of simulation B (independent draws from the fitted model, each fitted
like the recording) are whitened by the MODEL's residual level

    σ_s,c = RMS over the keyframe intervals of simulation A's residual, per column                       (BG1)

(what the model predicts its own residuals to be: the N-pose noise propagated through the graph; a recording
noisier than its model then counts), and compared by the single-IMU statistic (G1) of
imugraph.diagnose.gap (`channel_gap`, imported: W1 between the whitened distributions + whiteness term at
log-spaced lags up to 0.5 s on the channel's own time base, mean over the columns):

    gap_s,c = max(0, G1(real, A) − G1(B, A)),   null_s,c = G1(B, A)                                      (BG2)

≈ 0 when the data come from the model. Localisation: (G1) in sliding 4 s windows 1 s apart, real vs A and
the null curve B vs A; a window is flagged when it exceeds both 1.25 × the 99 % quantile of the null curve and
median + 3·MAD of the recording's own curve (as imugraph.diagnose.gap.localise); runs ≥ 2 s are locations.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.body.fit import CHANNELS, BodyFit
from imugraph.diagnose.gap import GapOptions, channel_gap, flag_runs, lag_grid, windows
from imugraph.folds import held_out_masks


def model_sigma(sim_a: BodyFit) -> dict:
    """(BG1): sensor → channel → (d,) RMS of simulation A's residuals (floored)."""
    out = {}
    for n, sf in sim_a.sensors.items():
        out[n] = {c: np.maximum(np.sqrt(np.nanmean(r**2, axis=0)), 1e-12) if r.shape[1] else np.ones(0)
                  for c, r in sf.residuals.items()}
    return out


def interval_rate(t: np.ndarray) -> float:
    return float(1.0 / np.median(np.diff(t)))


def pair_gap(r_real: np.ndarray, r_sim: np.ndarray, sigma: np.ndarray, mask: np.ndarray, lags: np.ndarray,
             opt: GapOptions = GapOptions()) -> float:
    """(G1) between two raw residual series (K, d) whitened by sigma (d,) over the rows in mask."""
    if r_real.shape[1] == 0:
        return 0.0
    return float(channel_gap(r_real / sigma, r_sim / sigma, mask, lags, opt))


def sensor_gaps(real: BodyFit, a: BodyFit, b: BodyFit, sigma: dict, mask=None, opt: GapOptions = GapOptions(),
                real_res: dict | None = None) -> dict:
    """sensor → channel → {"gap", "gap_raw", "null_gap"} (BG2) over the rows in mask (channel → row mask on
    that channel's time base; default all). real_res: optional {sensor: {channel: residuals}} replacing the real
    fit's (a corrected model)."""
    out = {}
    for n, sf in real.sensors.items():
        rr = (real_res or {}).get(n, sf.residuals)
        out[n] = {}
        for c in CHANNELS:
            tb = sf.time_base(c)
            lags = lag_grid(interval_rate(tb), opt)
            m = np.ones(tb.size, bool) if mask is None else mask[c]
            raw = pair_gap(rr[c], a.sensors[n].residuals[c], sigma[n][c], m, lags, opt)
            null = pair_gap(b.sensors[n].residuals[c], a.sensors[n].residuals[c], sigma[n][c], m, lags, opt)
            out[n][c] = {"gap": max(0.0, raw - null), "gap_raw": raw, "null_gap": null}
    return out


def curve(t: np.ndarray, r1: np.ndarray, r2: np.ndarray, sigma: np.ndarray, opt: GapOptions = GapOptions()):
    """(centres (W,), values (W,)) of (G1) of r1 vs r2 in sliding windows."""
    lags = lag_grid(interval_rate(t), GapOptions(max_lag_s=min(opt.max_lag_s, opt.window_s / 4), n_lags=opt.n_lags))
    starts, stops = windows(t, opt)
    vals = np.zeros(len(starts))
    for i, (s, e) in enumerate(zip(starts, stops)):
        vals[i] = pair_gap(r1[s:e], r2[s:e], sigma, np.ones(e - s, bool), lags, opt)
    centres = 0.5 * (t[starts] + t[np.maximum(stops - 1, starts)])
    return centres, vals


def localise(real: BodyFit, a: BodyFit, b: BodyFit, sigma: dict, opt: GapOptions = GapOptions()):
    """(curves, locations): curves[sensor][channel] = {"t", "real", "null", "threshold"}; locations =
    [{"sensor", "channel", "t_start", "t_end", "score"}], best score first (module doc)."""
    curves, locations = {}, []
    for n, sf in real.sensors.items():
        curves[n] = {}
        for c in CHANNELS:
            if sf.residuals[c].shape[1] == 0:
                continue
            tb = sf.time_base(c)
            tc, vals = curve(tb, sf.residuals[c], a.sensors[n].residuals[c], sigma[n][c], opt)
            _, null = curve(tb, b.sensors[n].residuals[c], a.sensors[n].residuals[c], sigma[n][c], opt)
            if not len(vals):
                continue
            thr, flagged = flag_runs(tc, vals, null, opt)
            curves[n][c] = {"t": tc, "real": vals, "null": null, "threshold": thr}
            locations += [{"sensor": n, "channel": c, "t_start": t0, "t_end": t1, "score": score}
                          for t0, t1, score in flagged]
    locations.sort(key=lambda d: -d["score"])
    return curves, locations


def channel_folds(sf, block_s: float = 2.0, n_folds: int = 5) -> list:
    """Per fold k: (train, test) = ({channel: row mask}, {channel: row mask}) on each channel's time base (the
    same 2 s blocks in time for every channel)."""
    per = {c: fold_masks(sf.time_base(c), block_s, n_folds, t0=float(sf.t_sample[0])) for c in CHANNELS}
    return [({c: per[c][k][0] for c in CHANNELS}, {c: per[c][k][1] for c in CHANNELS}) for k in range(n_folds)]


def fold_masks(t: np.ndarray, block_s: float = 2.0, n_folds: int = 5, t0: float | None = None) -> list:
    """Interleaved CV blocks (as the single-IMU attribution): block b of `block_s` belongs to fold b mod K;
    returns K (train, test) boolean row masks."""
    return [(~held, held) for held in held_out_masks(t, block_s, n_folds, t0)]
