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

Relevance (`size`): RMS of the Wiener estimate of n_a over the samples in motion ≥ the ordinary level of
the recording's own motion (L2), `ordinary_level`: between 0.3 g and g.

Injection ranges (RANGES): RMS |n_a| 1.2–2 g (11.8–19.6 m/s²: above the largest relevance threshold g of
(L2), so an injected case is clearly there on any host; fast hand-held translation: BROAD's fast
translation trials 15/16 reach 14–19 m/s² RMS in motion), Gaussian spectrum of width 0.3–1.5 Hz, over
the whole session; nav-frame signal put in the body frame with the
truth orientation (or the integrated gyro where it is unknown).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, injection_orientation,
                                             noise_scale, psd_filter, replace_session, train_psd)
from imugraph.io.validate import runs

RANGES = {"rms_ms2": (1.2 * 9.80665, 2.0 * 9.80665), "bandwidth_hz": (0.3, 1.5)}
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

    def log_det_per_sample(self, n: int, rate_hz: float) -> dict:
        """S20-W: channel → (1/n) ln|det W| of the whitening filter W that `raw_residuals` applies (a circulant
        filter |H(f)| per nav axis, rotated back orthogonally), summed over the axes:

            J_acc = Σ_axis mean_f ln|H_axis(f)|   (≤ 0: |H| ≤ 1)                                        (L3)

        The density of the raw residual r under (L1) is that of w = W r times |det W|, so the log score (A4)
        of the whitened residual w must add −J per sample to be the negative log-likelihood of r; without it
        a stronger filter (larger P, lower f_c) scores better whatever the data (nested.py (V''1))."""
        from imugraph.diagnose.nested import _mean_log_gain

        return {"acc": _mean_log_gain(self.deltas["gain"](n, rate_hz), n)}          # (F, 3) on rfftfreq(n)

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
        """RMS |n_a| over the samples in motion, m/s², against the ordinary level of (L2) (`ordinary_level`)."""
        a = corr.signal(fit)[motion_mask(fit)]
        a = a[np.all(np.isfinite(a), axis=1)]
        rms = float(np.sqrt(np.mean(np.sum(a**2, axis=1)))) if len(a) else 0.0
        return {"value": rms, "threshold": ordinary_level(fit), "unit": "m/s² RMS in motion"}


HAND_LEVER_M = 0.1       # lever arm of a hand-held sensor turned by the wrist (hand length ≈ 0.19 m: palm ≈ 0.1 m)
MOTION_SMOOTH_S = 0.1    # ω̂ and α̂ smoothed over this (hand motion < 5 Hz; keeps the gyro noise out of α̂)


def ordinary_level(fit) -> float:
    """Relevance threshold of linear_acceleration, m/s² RMS in motion (L2):

        a_ord = max(RELEVANT_G · g, min(g, r_h · RMS_motion √(|α̂|² + |ω̂|⁴)))                        (L2)

    A hand-held sensor always accelerates: turned about the wrist at lever arm r_h it feels the tangential
    |α × r| and centripetal |ω × (ω × r)| accelerations of the rotation the gyro measures (orthogonal for
    r ⊥ ω; r_h = HAND_LEVER_M), so that much linear acceleration is what the motion ordinarily brings, not
    an unmodelled effect worth naming — ω̂, α̂ from the fitted trajectory (smoothed over MOTION_SMOOTH_S).
    Bounds: never below 0.3 g (a gravity-only tilt errs by > ~15°: below that nothing is worth naming), and
    never above g (at an RMS of g the accelerometer no longer indicates the vertical, whatever the
    rotation). Slow hand-held rotation (≈ 2.5 rad/s RMS, α̂ ≈ 6 rad/s²) stays at 0.3 g; fast rotation
    (6–9 rad/s, 50–120 rad/s²) reaches 0.7–1 g, fast translation with little rotation stays near 0.3 g."""
    from imugraph.diagnose.effects.base import smooth

    g = STANDARD_G
    n = max(1, int(round(MOTION_SMOOTH_S * fit.session.rate)))
    w = smooth(np.asarray(fit.b_omega, float), n)
    alpha = smooth(np.gradient(w, fit.session.t, axis=0), n)
    k2 = np.sum(alpha**2, axis=1) + np.sum(w**2, axis=1) ** 2
    m = motion_mask(fit) & np.isfinite(k2)
    rot = HAND_LEVER_M * float(np.sqrt(np.mean(k2[m]))) if m.any() else 0.0
    return float(max(RELEVANT_G * g, min(g, rot)))

EFFECT = LinearAcceleration()
