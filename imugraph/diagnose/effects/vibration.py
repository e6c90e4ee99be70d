"""vibration: a narrow-band oscillation of the accelerometer over a time window (a vibrating motor or
phone on the sensor's mount).

Model, in window w: b_acc,j = bRn,j (0, 0, g) + v_j + e_a, v a narrow-band process around f₀ with
per-axis spectrum S_v,a(f) (zero outside the band f₀ ± Δf).                                          (V1)

Fit: windows from the high-pass accelerometer residual (residual minus its 0.2 s moving mean) of all
samples — moving mean of its squared whitened norm well above its quiet level (base.detect_windows; the
window edges are the localisation, like magnetic_disturbance's) or the `window` argument. Spectra over the
training samples only: S_in inside the windows, S_out outside (Welch, ≈ 1 s segments); f₀ = the peak of
S_in/S_out above 5 Hz, the band = the contiguous bins where that ratio exceeds a quarter of its peak (one
bin of margin), S_v = max(S_in − S_out, 0) in the band.

Residuals (base rule 2): inside the windows, the accelerometer residual passed through the extended
model's whitening filter |H(f)| = √(S_out / (S_out + S_v)) (zero phase); unchanged outside.

Relevance (`size`): band RMS ≥ 0.3 m/s².

Injection ranges (RANGES): f₀ = 20–80 Hz (at most 0.4 × the sampling rate), amplitude 0.6–3 m/s², random
direction, slow frequency wander ±2 %, window 15–40 % of the session, raised-cosine ramps 0.1–0.5 s.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, detect_windows, envelope,
                                             noise_scale, psd_filter, random_window, replace_session, smooth,
                                             train_psd, window_mask)
from imugraph.io.validate import runs

RANGES = {"freq_hz": (20.0, 80.0), "amp_ms2": (0.6, 3.0), "window_frac": (0.15, 0.4), "ramp_s": (0.1, 0.5)}
MAX_WINDOWS = 3
RELEVANT_RMS = 0.3           # relevance: band RMS ≥ 0.3 m/s² (≈ 10× a MEMS accelerometer's white noise)


class VibrationCorrection(Correction):
    def raw_residuals(self, fit) -> dict:
        out = {c: fit.residuals[c].copy() for c in fit.residuals}
        wins = self.params["windows"]
        if not wins:
            return out
        f_w, s_out, s_v = self.deltas["f"], self.deltas["s_out"], self.deltas["s_v"]
        f_full = np.fft.rfftfreq(fit.n)
        gain = np.stack([np.sqrt(np.interp(f_full, f_w, s_out[:, a]) /
                                 (np.interp(f_full, f_w, s_out[:, a]) + np.interp(f_full, f_w, s_v[:, a])))
                         for a in range(3)], axis=1)
        filt = psd_filter(fit.residuals["acc"], gain)
        inside = window_mask(fit.session.t, [(w["t_start"], w["t_end"]) for w in wins])
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
        inside = window_mask(s.t, wins)
        a0, a1 = runs(train)
        nper = int(2 ** np.clip(np.floor(np.log2(min(rate, int(np.max(a1 - a0))))), 4, 12))  # ≤ 1 s
        f, s_in = train_psd(r, train & inside, nper)
        _, s_out = train_psd(r, train & ~inside, nper)
        if not wins or not np.all(np.isfinite(s_in)) or not np.all(np.isfinite(s_out)):
            return VibrationCorrection(self.name, {"windows": []}, n_params=0, channel=self.channel)
        ratio = s_in.sum(axis=1) / np.maximum(s_out.sum(axis=1), 1e-30)
        ratio[f * rate < 5.0] = 0.0
        k0 = int(np.argmax(ratio))
        band = ratio > ratio[k0] / 4.0
        lo = hi = k0
        while lo > 0 and band[lo - 1]:
            lo -= 1
        while hi < len(f) - 1 and band[hi + 1]:
            hi += 1
        lo, hi = max(lo - 1, 0), min(hi + 1, len(f) - 1)
        s_v = np.zeros_like(s_in)
        s_v[lo:hi + 1] = np.maximum(s_in[lo:hi + 1] - s_out[lo:hi + 1], 0.0)
        params = {"windows": [{"t_start": a, "t_end": b} for a, b in wins], "freq_hz": float(f[k0] * rate),
                  "band_hz": [float(f[lo] * rate), float(f[hi] * rate)],
                  "amp_ms2": np.sqrt(2 * np.sum(s_v, axis=0) / nper).tolist()}
        corr = VibrationCorrection(self.name, params, n_params=2 * len(wins) + 5,
                                   t_start=wins[0][0], t_end=wins[0][1], channel=self.channel,
                                   deltas={"f": f, "s_out": s_out, "s_v": s_v})
        corr.deltas["noise_scale"] = noise_scale(fit, corr.raw_residuals(fit), train, ["acc"])
        return corr

    @staticmethod
    def find_windows(fit) -> list:
        """Vibration windows (t_start, t_end) from the high-pass accelerometer residual of all samples."""
        s = fit.session
        r = fit.residuals["acc"]
        hp = r - smooth(r, int(round(0.2 * s.rate)))
        z2 = np.sum((hp / fit.sigma["acc"]) ** 2, axis=1) / 3.0
        found = detect_windows(s.t, z2, smooth_s=0.5, factor=4.0, min_s=2.0, merge_s=1.0)[:MAX_WINDOWS]
        return [(float(s.t[a]), float(s.t[b - 1])) for a, b in found]


    def size(self, corr, fit) -> dict:
        """RMS of the band-limited excess acceleration in the windows, m/s² (relevance ≥ 0.3 m/s²)."""
        amp = np.asarray(corr.params.get("amp_ms2", [0.0, 0.0, 0.0]), float)
        return {"value": float(np.linalg.norm(amp) / np.sqrt(2.0)), "threshold": RELEVANT_RMS,
                "unit": "m/s² RMS"}


EFFECT = Vibration()
