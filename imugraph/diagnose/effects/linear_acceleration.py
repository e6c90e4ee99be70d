"""linear_acceleration: the sensor translates, so the accelerometer also measures its acceleration.

Model (DESIGN.md (S2) with n_acc ≠ 0): b_acc,j = bRn,j (n_a,j + (0, 0, g)) + e_a, with the nav-frame
acceleration n_a a stationary low-pass Gaussian process, per axis group (horizontal x,y; vertical z):

    S_a(f) = P_grp / (1 + (f / f_c)⁴)           (a second-order low-pass spectrum; f_c ≤ a few Hz)     (L1)

Fit (training samples only): the nav-frame residual â_j = R̂_j acc_j (first order: â = n_a + noise) has the
spectrum S_a(f) + σ_f², σ_f² the white floor; Welch spectra over the training runs (segments ≤ 8 s that fit
in a run) give σ_f² (median of the
upper half band) and (P_h, P_v, f_c) by least squares on log-spectra over a grid of f_c.

Residuals (base rule 2): the nav-frame residual passed through the extended model's whitening filter
|H(f)| = √(σ_f² / (σ_f² + S_a(f))) (zero phase), rotated back to the body frame: white at σ_f when (L1)
holds. The filter is fixed by the training samples; it fits nothing to the held-out ones.

Relevance (`size`): RMS of the Wiener estimate of n_a over the samples in motion ≥ 0.3 g.

Injection ranges (RANGES): RMS |n_a| 3.5–8 m/s² (above the relevance threshold of 0.3 g ≈ 2.9 m/s²: the
harness injects effects that matter; fast hand-held translation; BROAD's fast
translation trial 16 reaches a median |R·acc − g| ≈ 13.6 m/s² in motion), band 0.2–2 Hz (Gaussian
spectrum of width 0.3–1.5 Hz), over the whole session; nav-frame signal put in the body frame with the
truth orientation (or the integrated gyro where it is unknown).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, injection_orientation,
                                             noise_scale, psd_filter, replace_session, train_psd)
from imugraph.io.validate import runs

RANGES = {"rms_ms2": (3.5, 8.0), "bandwidth_hz": (0.3, 1.5)}
FC_GRID_HZ = np.geomspace(0.05, 8.0, 24)


def lowpass_shape(f_hz: np.ndarray, fc: float) -> np.ndarray:
    """(L1) spectrum shape 1 / (1 + (f/f_c)⁴)."""
    return 1.0 / (1.0 + (np.asarray(f_hz) / fc) ** 4)


RELEVANT_G = 0.3     # relevance: RMS |n_a| during motion ≥ 0.3 g (a gravity-only tilt then errs by > ~15°)
STANDARD_G = 9.80665  # m/s²: the threshold is in units of standard gravity, not of the fitted g (which the base
                      # model inflates when linear acceleration is present: BROAD 15 fits g = 16.9 m/s²)


def motion_mask(fit) -> np.ndarray:
    """(N,) samples in motion: not in the rest mask of the fit's initial calibration (all when unknown)."""
    rest = fit.info.get("rest")
    if rest is None or np.shape(rest) != (fit.n,):
        return np.ones(fit.n, bool)
    m = ~np.asarray(rest, bool)
    return m if m.sum() >= 10 else np.ones(fit.n, bool)


class LinearAccelerationCorrection(Correction):
    def signal(self, fit) -> np.ndarray:
        """(N, 3) nav-frame linear acceleration, the Wiener estimate from the residual:
        n_a = F⁻¹[(S_a / (S_a + σ_f²)) · F(â)] = â − F⁻¹[|H|² F(â)]  (L1)."""
        a_n = np.einsum("nij,nj->ni", fit.nRb, fit.residuals["acc"])
        gain = self.deltas["gain"](len(a_n), fit.session.rate)
        return a_n - psd_filter(a_n, gain**2)

    def corrected(self, fit) -> dict:
        """acc with the estimated linear acceleration removed: y − R̂ᵀ n_a."""
        a_n = np.nan_to_num(self.signal(fit))
        return {"acc": fit.session.acc - np.einsum("nji,nj->ni", fit.nRb, a_n)}

    def raw_residuals(self, fit) -> dict:
        out = {c: fit.residuals[c].copy() for c in fit.residuals}
        a_n = np.einsum("nij,nj->ni", fit.nRb, fit.residuals["acc"])               # â = R̂ r_acc
        gain = self.deltas["gain"](len(a_n), fit.session.rate)
        w = psd_filter(a_n, gain)
        out["acc"] = np.einsum("nji,nj->ni", fit.nRb, w)                             # back to body
        return out


class LinearAcceleration(Effect):
    name = "linear_acceleration"
    channel = "acc"
    windowed = False
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """Add bRn·n_a, n_a band-limited noise scaled to an RMS |n_a| (strength, m/s²)."""
        rms = float(strength) if strength is not None else float(rng.uniform(*RANGES["rms_ms2"]))
        bw = float(rng.uniform(*RANGES["bandwidth_hz"]))
        n = session.n
        rate = session.rate
        f = np.fft.rfftfreq(n, 1.0 / rate)
        spec = np.exp(-0.5 * (f / bw) ** 2)
        spec[0] = 0.0
        noise = rng.standard_normal((n, 3))
        a_n = np.fft.irfft(np.fft.rfft(noise, axis=0) * spec[:, None], n=n, axis=0)
        a_n *= np.array([1.0, 1.0, rng.uniform(0.3, 1.0)])                         # less vertical
        a_n *= rms / np.sqrt(np.mean(np.sum(a_n**2, axis=1)))
        nRb = injection_orientation(session)
        acc = session.acc + np.einsum("nji,nj->ni", nRb, a_n)                       # + bRn n_a (S2)
        truth = {"params": {"rms_ms2": rms, "bandwidth_hz": bw}, "t_start": None, "t_end": None}
        return replace_session(session, acc=acc, name_suffix="+linear_acceleration",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        train = check_train(fit, train)
        rate = fit.session.rate
        a_n = np.einsum("nij,nj->ni", fit.nRb, fit.residuals["acc"])
        a0, a1 = runs(train)
        longest = int(np.max(a1 - a0))
        nper = int(2 ** np.clip(np.floor(np.log2(min(8.0 * rate, longest))), 5, 13))  # ≤ 8 s, fits a run
        f, S = train_psd(a_n, train, nper)
        f_hz = f * rate
        floor = np.median(S[f_hz > 0.25 * rate], axis=0)                             # σ_f² per axis
        sig2 = float(np.mean(floor))
        use = (f_hz > 0) & (f_hz < 0.25 * rate)
        groups = {"h": S[:, :2].mean(axis=1), "v": S[:, 2]}
        best = None
        for fc in FC_GRID_HZ:
            L = lowpass_shape(f_hz[use], fc)
            cost, Ps = 0.0, {}
            for g, s in groups.items():
                excess = np.maximum(s[use] - sig2, 0.0)
                P = max(float(np.sum(L * excess) / np.sum(L * L)), 0.0)
                cost += float(np.sum((np.log(s[use]) - np.log(sig2 + P * L)) ** 2))
                Ps[g] = P
            if best is None or cost < best[0]:
                best = (cost, fc, Ps)
        _, fc, Ps = best
        P_axes = np.array([Ps["h"], Ps["h"], Ps["v"]])

        def gain(n, rate_hz, fc=fc, P=P_axes, s2=sig2):
            fh = np.fft.rfftfreq(n, 1.0 / rate_hz)
            return np.sqrt(s2 / (s2 + np.outer(lowpass_shape(fh, fc), P)))          # |H(f)| per axis

        corr = LinearAccelerationCorrection(
            self.name, {"fc_hz": float(fc), "psd_h": float(Ps["h"]), "psd_v": float(Ps["v"]),
                        "white_floor": sig2,
                        "rms_ms2": float(np.sqrt(np.sum(P_axes) * fc / rate * np.pi / np.sqrt(2)))},
            n_params=4, channel=self.channel, deltas={"gain": gain})
        res = corr.raw_residuals(fit)
        corr.deltas["noise_scale"] = noise_scale(fit, res, train, ["acc"])
        return corr


    def size(self, corr, fit) -> dict:
        """RMS |n_a| over the samples in motion, m/s² (threshold RELEVANT_G · g)."""
        a = corr.signal(fit)[motion_mask(fit)]
        a = a[np.all(np.isfinite(a), axis=1)]
        rms = float(np.sqrt(np.mean(np.sum(a**2, axis=1)))) if len(a) else 0.0
        return {"value": rms, "threshold": RELEVANT_G * STANDARD_G, "unit": "m/s² RMS in motion"}


EFFECT = LinearAcceleration()
