"""vibration: a narrow-band oscillation of the accelerometer over a time window (a vibrating motor or
phone on the sensor's mount).

Model, in window w: b_acc,j = bRn,j (0, 0, g) + v_j + e_a, v a narrow-band process around f₀ with
per-axis spectrum S_v,a(f) (zero outside the band f₀ ± Δf).                                          (V1)

Fit: windows from the accelerometer residual of all samples above the motion band: human movement,
physiological tremor (8–12 Hz) included, puts (almost) no acceleration above MOTION_BAND_HZ = 15 Hz, a
motor's or a vehicle's vibration does (V2); the residual is high-passed there (zero phase, FFT) and the
moving mean (0.5 s) of its squared norm is flagged well above its quiet level (base.detect_windows; the
window edges are the localisation, like magnetic_disturbance's), or the `window` argument. (A 0.2 s
moving-mean high-pass let enough hand-motion energy of the fast-rotation crops through that no window
stood out.) Spectra over the
training samples only: S_in inside the windows, S_out outside (Welch, ≈ 1 s segments); f₀ = the peak of
S_in/S_out above MOTION_BAND_HZ, the band = the contiguous bins where that ratio exceeds a quarter of its peak (one
bin of margin), S_v,w = max(S_w − S_out, 0) in the band, per window w (S_w: the
window's own training spectrum); a window whose band RMS is below half the relevance threshold holds no
vibration and is dropped (kept when it is the only one).

Residuals (base rule 2): inside the windows, the accelerometer residual passed through the extended
model's whitening filter |H_w(f)| = √(S_out / (S_out + S_v,w)) (zero phase); unchanged outside.
The reported window (t_start, t_end) and amplitude are those of the window with the largest band RMS.

Band windows (S16-F, opt-in: BAND_WINDOWS / DiagnoseOptions.vibration_band_windows, default off). (V2)'s
windows are where the residual has power above the motion band — a narrow-band vibration, but also a
broadband transient of the host (a knock, the sensor put down: BROAD 04's "breaks"), which (V2) merges with
or adds to the vibration's window. The model (V1) claims a band only, so with the option the windows are
localised a second time on the residual band-passed to the fitted band f_lo..f_hi (± 1 Hz), same moving
mean and threshold as (V2) (V3), and a window is kept only when most of its excess power above the motion
band lies in the band:

    ρ_w = (P_band,w − P_band,quiet) / (P_above,w − P_above,quiet) ≥ ½       (narrow-band excess)      (V4)

(P: the 0.5 s moving mean of the squared norm of the band-passed / above-motion-band residual, tested
sample by sample, so that a transient inside or next to the vibration is cut out; quiet: its 20 % quantile
over the recording, as in detect_windows). A transient spreads its power over 15 Hz … rate/2, of
which a few-Hz band holds a few per cent. The spectra (S_in, S_out, the band, S_v,w) are then estimated
again with the windows of (V3)–(V4). Why: a broadband transient claimed as vibration keeps its residual
(outside the band nothing is whitened) while the extended model's σ, estimated on the whitened window,
is smaller — the held-out log score (A4) of the fold that holds the transient turns negative and the sign
test (A4'') rejects the vibration (harness seed 2, cases 015/016: fold gains −0.15 / −0.44 nats, all
others +0.20 … +1.08; docs/diagnose.md §S16-F).

Relevance (`size`): band RMS ≥ 0.3 m/s².

Motion check (S20-V: MOTION_CHECK / DiagnoseOptions.vibration_motion_check, default since session 20). (V2) takes
everything above 15 Hz for a vibration, but a hand's fast rotation has a broadband tail there that the gyro
measures too (BROAD 07 whole: band 14.5–25.7 Hz at the motion band's edge, 0.53 m/s² in the window of
motion; the phone motor of 26 is a line at 40.2 Hz, 2.92 m/s²). With the option the relevance also asks for
more than the band RMS that the measured rotation explains at a hand's lever arm, as linear_acceleration's
(L2) does for the low band ((V6), `motion_band_rms`; the threshold becomes max(0.3 m/s², that RMS)).

Injection ranges (RANGES): f₀ = 20–80 Hz (above the motion band; motors, hand tools and engines vibrate at tens
of Hz) (at most 0.4 × the sampling rate), amplitude 0.6–3 m/s², random
direction, slow frequency wander ±2 %, window 15–40 % of the session, raised-cosine ramps 0.1–0.5 s.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, detect_windows, envelope,
                                             flag_windows, noise_scale, psd_filter, random_window, replace_session,
                                             smooth, train_psd, window_mask)
from imugraph.io.validate import runs

RANGES = {"freq_hz": (20.0, 80.0), "amp_ms2": (0.6, 3.0), "window_frac": (0.15, 0.4), "ramp_s": (0.1, 0.5)}
MAX_WINDOWS = 3
MOTION_BAND_HZ = 15.0        # human movement (incl. physiological tremor, 8–12 Hz) stays below this (V2)
RELEVANT_RMS = 0.3           # relevance: band RMS ≥ 0.3 m/s² (≈ 10× a MEMS accelerometer's white noise)
BAND_WINDOWS = True          # S16-F (V3)–(V4): windows re-localised on the fitted band, narrow-band excess only (default since S16)
BAND_MARGIN_HZ = 1.0         # (V3): band-pass f_lo − 1 Hz … f_hi + 1 Hz (the ±2 % wander of f₀ stays inside)
NARROW_SHARE = 0.5           # (V4): share of the window's above-motion-band excess power inside the band
MOTION_CHECK = True          # S20-V (V6): relevance ≥ the band RMS the measured angular motion explains (default since S20)


def above_motion_band(x: np.ndarray, rate: float) -> np.ndarray:
    """x (N, d) high-passed (zero phase) above MOTION_BAND_HZ, with a raised-cosine transition of
    1 Hz: what hand and body motion do not reach (V2)."""
    f_hz = np.fft.rfftfreq(len(x), 1.0 / rate)
    ramp = np.clip((f_hz - MOTION_BAND_HZ) / 1.0 + 0.5, 0.0, 1.0)
    return psd_filter(x, 0.5 * (1.0 - np.cos(np.pi * ramp)))


def band_pass(x: np.ndarray, rate: float, f_lo: float, f_hi: float) -> np.ndarray:
    """x (N, d) band-passed (zero phase) to f_lo … f_hi Hz with raised-cosine transitions of 1 Hz (V3)."""
    f_hz = np.fft.rfftfreq(len(x), 1.0 / rate)
    up = np.clip((f_hz - f_lo) / 1.0 + 0.5, 0.0, 1.0)
    down = np.clip((f_hi - f_hz) / 1.0 + 0.5, 0.0, 1.0)
    return psd_filter(x, 0.25 * (1.0 - np.cos(np.pi * up)) * (1.0 - np.cos(np.pi * down)))


def band_spectra(r: np.ndarray, train: np.ndarray, inside: np.ndarray, nper: int, rate: float):
    """(f, S_out, k0, lo, hi) of (V1)'s fit: Welch spectra of the residual r inside / outside the windows
    (training samples), f₀'s bin k0 = the peak of S_in/S_out above the motion band and the band's bins
    lo..hi (ratio > peak/4, one bin of margin); None when a spectrum cannot be estimated."""
    f, s_in = train_psd(r, train & inside, nper)
    _, s_out = train_psd(r, train & ~inside, nper)
    if not np.all(np.isfinite(s_in)) or not np.all(np.isfinite(s_out)):
        return None
    ratio = s_in.sum(axis=1) / np.maximum(s_out.sum(axis=1), 1e-30)
    ratio[f * rate < MOTION_BAND_HZ] = 0.0
    k0 = int(np.argmax(ratio))
    band = ratio > ratio[k0] / 4.0
    lo = hi = k0
    while lo > 0 and band[lo - 1]:
        lo -= 1
    while hi < len(f) - 1 and band[hi + 1]:
        hi += 1
    return f, s_out, k0, max(lo - 1, 0), min(hi + 1, len(f) - 1)


def band_windows(fit, f_lo_hz: float, f_hi_hz: float) -> list:
    """(V3)–(V4): windows (t_start, t_end) where the residual's power in the band f_lo … f_hi (± BAND_MARGIN_HZ)
    is well above its quiet level AND holds most of the excess power above the motion band, both on the
    0.5 s moving mean (a transient inside or next to a vibration is cut out at that resolution); runs
    closer than 1 s merged, shorter than 2 s dropped (as (V2)); longest first."""
    s = fit.session
    r = fit.residuals["acc"]
    n = int(round(0.5 * s.rate))
    p_band = smooth(np.sum(band_pass(r, s.rate, f_lo_hz - BAND_MARGIN_HZ, f_hi_hz + BAND_MARGIN_HZ) ** 2, axis=1), n)
    p_above = smooth(np.sum(above_motion_band(r, s.rate) ** 2, axis=1), n)
    ok = np.isfinite(p_band) & np.isfinite(p_above)
    if ok.sum() < 10:
        return []
    q_band = max(float(np.quantile(p_band[ok], 0.2)), 1e-12)
    q_above = float(np.quantile(p_above[ok], 0.2))
    flag = ok & (p_band > 4.0 * q_band)                                                              # (V3)
    flag &= (p_band - q_band) >= NARROW_SHARE * np.maximum(p_above - q_above, 0.0)                  # (V4)
    found = flag_windows(s.t, flag, merge_s=1.0, min_s=2.0)
    return [(float(s.t[i0]), float(s.t[i1 - 1])) for i0, i1 in found[:MAX_WINDOWS]]


def motion_band_rms(fit, train: np.ndarray, wins: list, nper: int, lo: int, hi: int, k: int) -> float:
    """(V6) in window k of `wins`: the band RMS of the accelerometer excess that the MEASURED angular motion explains
    at a hand's lever arm r_h (linear_acceleration.HAND_LEVER_M, as (L2)). A rigid body turning at ω feels at
    r the tangential α × r and the centripetal ω × (ω × r); above the motion band the part that varies fast is
    α_hf × r and, to first order, ω̄ × (ω_hf × r) + ω_hf × (ω̄ × r) (ω̄: the slow rate), so per axis

        u = r_h (ω̇ + 2 |ω̄| ω),   ω = y_gyr − b̂ (the gyro, not the fit),                               (V6)

    (|α × r| ≤ |α| r_h; the two terms are in quadrature at each frequency, so their powers add) and its
    excess in the window over the outside, band bins lo..hi, in (V1)'s own estimator and units:
    P_w = Σ_axes Σ_band max(S_u,w − S_u,out, 0) / nper (the gyro's white noise cancels in the difference).
    A hand's fast rotation has a broadband tail above 15 Hz that the gyro sees too (BROAD 07); a motor or a
    phone vibrates the accelerometer far beyond what its rotation explains (26)."""
    from imugraph.diagnose.effects.linear_acceleration import HAND_LEVER_M, MOTION_SMOOTH_S

    s = fit.session
    w = np.asarray(s.gyr, float) - np.nan_to_num(np.asarray(fit.b_gyr_bias, float))
    w_bar = smooth(np.linalg.norm(w, axis=1), max(1, int(round(MOTION_SMOOTH_S * s.rate))))
    u = HAND_LEVER_M * (np.gradient(w, s.t, axis=0) + 2.0 * w_bar[:, None] * w)                     # (V6)
    _, u_out = train_psd(u, train & ~window_mask(s.t, wins), nper)
    _, u_w = train_psd(u, train & window_mask(s.t, [wins[k]]), nper)
    ex = np.maximum(u_w[lo:hi + 1] - u_out[lo:hi + 1], 0.0)
    return float(np.sqrt(np.sum(ex) / nper)) if np.all(np.isfinite(ex)) else 0.0


class VibrationCorrection(Correction):
    def window_gains(self, n: int):
        """(window, |H_w| (F, 3) on rfftfreq(n)) per window: its whitening gain (V1) √(S_out / (S_out + S_v,w)),
        each window its own S_v (`raw_residuals`, and its Jacobian in nested.log_det)."""
        f_w, s_out = self.deltas["f"], self.deltas["s_out"]
        f_full = np.fft.rfftfreq(n)
        so = np.stack([np.interp(f_full, f_w, s_out[:, a]) for a in range(3)], axis=1)
        for w, s_v in zip(self.params["windows"], self.deltas["s_v"]):
            sv = np.stack([np.interp(f_full, f_w, s_v[:, a]) for a in range(3)], axis=1)
            yield w, np.sqrt(so / np.maximum(so + sv, 1e-30))

    def raw_residuals(self, fit) -> dict:
        out = {c: fit.residuals[c].copy() for c in fit.residuals}
        if not self.params["windows"]:
            return out
        for w, gain in self.window_gains(fit.n):
            filt = psd_filter(fit.residuals["acc"], gain)
            inside = window_mask(fit.session.t, [(w["t_start"], w["t_end"])])
            out["acc"][inside] = filt[inside]
        return out


class Vibration(Effect):
    name = "vibration"
    channel = "acc"
    windowed = True
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """Add (V1)'s oscillation over a window. strength: amplitude in m/s²."""
        amp = float(strength) if strength is not None else float(rng.uniform(*RANGES["amp_ms2"]))
        f_hi = min(RANGES["freq_hz"][1], 0.4 * session.rate)
        f0 = float(rng.uniform(min(RANGES["freq_hz"][0], 0.5 * f_hi), f_hi))
        window = tuple(window) if window is not None else random_window(session, rng, RANGES["window_frac"])
        ramp = float(rng.uniform(*RANGES["ramp_s"]))
        t = session.t
        freq = f0 * (1.0 + 0.02 * np.sin(2 * np.pi * t / rng.uniform(2.0, 10.0) + rng.uniform(0, 6.3)))
        phase = 2 * np.pi * np.cumsum(freq * session.dt) + rng.uniform(0, 2 * np.pi)
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        v = envelope(t, window, ramp)[:, None] * amp * np.sin(phase)[:, None] * d
        truth = {"params": {"freq_hz": f0, "amp_ms2": amp, "direction": d.tolist(), "ramp_s": ramp},
                 "t_start": window[0], "t_end": window[1]}
        return replace_session(session, acc=session.acc + v, name_suffix="+vibration",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        train = check_train(fit, train)
        s = fit.session
        rate = s.rate
        r = fit.residuals["acc"]
        wins = [tuple(map(float, window))] if window is not None else self.find_windows(fit)
        a0, a1 = runs(train)
        nper = int(2 ** np.clip(np.floor(np.log2(min(rate, int(np.max(a1 - a0))))), 4, 12))  # ≤ 1 s
        spec = band_spectra(r, train, window_mask(s.t, wins), nper, rate) if wins else None
        if spec is not None and window is None and BAND_WINDOWS:                          # (V3)–(V4)
            f, _, _, lo, hi = spec
            wins = band_windows(fit, f[lo] * rate, f[hi] * rate)
            spec = band_spectra(r, train, window_mask(s.t, wins), nper, rate) if wins else None
        if not wins or spec is None:
            return VibrationCorrection(self.name, {"windows": []}, n_params=0, channel=self.channel)
        f, s_out, k0, lo, hi = spec
        s_vs, amps = [], []
        for a, b in wins:                       # per window: a spurious window gets S_v ≈ 0 (no change)
            _, s_w = train_psd(r, train & window_mask(s.t, [(a, b)]), nper)
            s_v = np.zeros_like(s_out)
            if np.all(np.isfinite(s_w)):
                s_v[lo:hi + 1] = np.maximum(s_w[lo:hi + 1] - s_out[lo:hi + 1], 0.0)
            s_vs.append(s_v)
            amps.append(np.sqrt(2 * np.sum(s_v, axis=0) / nper))
        keep = [i for i, amp in enumerate(amps) if np.linalg.norm(amp) / np.sqrt(2) >= 0.5 * RELEVANT_RMS]
        if not keep:                                       # no window holds a band excess: nothing found
            keep = [int(np.argmax([np.linalg.norm(a) for a in amps]))]
        wins, s_vs, amps = [wins[i] for i in keep], [s_vs[i] for i in keep], [amps[i] for i in keep]
        best = int(np.argmax([np.linalg.norm(a) for a in amps]))
        params = {"windows": [{"t_start": a, "t_end": b, "amp_ms2": amp.tolist()} for (a, b), amp in zip(wins, amps)],
                  "freq_hz": float(f[k0] * rate), "band_hz": [float(f[lo] * rate), float(f[hi] * rate)],
                  "amp_ms2": amps[best].tolist()}
        if MOTION_CHECK:                                                                  # (V6)
            params["motion_rms"] = motion_band_rms(fit, train, wins, nper, lo, hi, best)
        corr = VibrationCorrection(self.name, params, n_params=5 + 5 * len(wins),
                                   t_start=wins[best][0], t_end=wins[best][1], channel=self.channel,
                                   deltas={"f": f, "s_out": s_out, "s_v": s_vs})
        corr.deltas["noise_scale"] = noise_scale(fit, corr.raw_residuals(fit), train, ["acc"])
        return corr

    @staticmethod
    def find_windows(fit) -> list:
        """Vibration windows (t_start, t_end) from the accelerometer residual of all samples above the
        motion band (V2): its power, moving mean over 0.5 s, well above its quiet level."""
        s = fit.session
        z2 = np.sum(above_motion_band(fit.residuals["acc"], s.rate) ** 2, axis=1)
        found = detect_windows(s.t, z2, smooth_s=0.5, factor=4.0, min_s=2.0, merge_s=1.0)[:MAX_WINDOWS]
        return [(float(s.t[a]), float(s.t[b - 1])) for a, b in found]


    def size(self, corr, fit) -> dict:
        """RMS of the band-limited excess acceleration in the windows, m/s² (relevance ≥ 0.3 m/s²; with
        MOTION_CHECK (V6) also ≥ the band RMS the measured angular motion explains in the same window):

            relevant ⇔ a_band ≥ max(RELEVANT_RMS, a_motion)                                         (V6')"""
        amp = np.asarray(corr.params.get("amp_ms2", [0.0, 0.0, 0.0]), float)
        out = {"value": float(np.linalg.norm(amp) / np.sqrt(2.0)), "threshold": RELEVANT_RMS, "unit": "m/s² RMS"}
        if "motion_rms" in corr.params:                                                   # (V6')
            out["motion_rms"] = float(corr.params["motion_rms"])
            out["threshold"] = max(RELEVANT_RMS, out["motion_rms"])
        return out


EFFECT = Vibration()
