"""timestamp_jitter: the samples are stamped on arrival at a host (PC receive time), not when sensed.

Model: the sensor samples on its own uniform clock; sample j is sensed at τ_j and stamped at t_j:

    τ_j = T₀ + Δ·k_j,   k_j integer, k_{j+1} − k_j ≥ 1 (a step > 1: samples lost on the link),
    t_j = τ_j + d_j,    d_j ≥ 0 the receive delay (buffering, radio/USB scheduling)                   (J1)

The base model integrates the gyro over the STAMPED steps Δt_j = t_{j+1} − t_j, so the rotation of
sample j is (y_j − δ_ω)·Δt_j where it was (y_j − δ_ω)·Δτ_j. On the base model's time base (the stamps,
kept: acc and mag pair with the orientation by sample index, not by time) the effect is the gyro
correction

    Δω_j = (y_j − δ_ω)·(Δτ_j / Δt_j − 1)      (y' = y + Δω integrates to the clock's rotation)        (J2)

whose residuals are evaluated exactly (`gyro_exact`, effects/base.py rule 1). Over a keyframe interval [a, b] at a steady rate ω the
stamped integration errs by ω·(d_b − d_a): a jitter of a few ms is many σ of the keyframe-mismatch
residual (σ_ω/√M) while the body turns.

Fit: the sample clock from the stamps alone (J3), (J5) — imugraph/diagnose/sample_clock.py.

When the two starts give different clocks (the trade between a period and lost samples when the jitter
nears a period), the one whose re-timed base fit closes best is kept (J7, `CHOOSE_BY_CLOSING`): the lower
RMS keyframe closing error ε_k (`closing_error_deg`), the rotation by which the gyro integrated over an
interval misses the next keyframe — the clock under which the gyro agrees with acc and mag (eV50p
MPU6500: (J3) preferred 17 lost samples at 11.554 ms, ε 0.36°; the other start 0 lost, ε 0.07°) — among the
candidates whose stamps deviate from them by a robust RMS ≤ 2 samples (J7'): twice the spread up to which
injected clocks are identified (mean delay 1 period: 0.71); set after V1000 LSM9DS0, whose second start
(10.928 ms, 37 lost, spread 11.3 samples) closed better (ε 2.23 vs 2.94°, both ≫ the other files' 0.07–0.26°:
no clock makes its gyro agree) while the robot says it is worse (0.2 s rotation error 8.88° vs 4.25°).
Uniform stamps (a recording stamped by its own clock, BROAD, simulations) are their own clock: Δω = 0.
The extended model's residuals: the gyro residual (R1) on the CLOCK's time base (J4, `JitterCorrection`);
its full refit (`refit`) is the base model fitted to the recording re-timed on the clock — exact, where
the alternation on Δω is not (Δω holds the base fit's bias, itself bent by the stamps); the screening
scores that refit too (J6, `SCREEN_REFIT`): with the keyframes of the base fit held, bent by the stamps
(the gyro σ is tiny, so the keyframes follow the stamped integration), the first-order Δω alone
(SCREEN_REFIT False) screened (A2) −1.3 to −5.1 on the four V1000 files, was never refitted there and left
the verdict linear_acceleration; refitted, (A2) +0.66 to +0.88 (docs/diagnose.md §S20-T).

Relevance (`size`): the robust RMS (1.4826·MAD) of the stamps' deviation from the fitted clock,
d_j − median(d), in sample periods ≥ 1/√12 ≈ 0.29: a stamp rounded to the sample grid errs by ±½ sample,
RMS 1/√12 — beyond that the stamps do not state when the samples were sensed. The orientation error the
stamps cause (RMS over keyframe intervals of |Σ (y − δ_ω)(Δt − Δτ)|, degrees) is reported beside it.

Injection (RANGES): a receive delay d_j exponential with mean 0.5–1 sample period (robust RMS 0.36–0.71
samples, above relevance; Rasteiro after its first burst: 0.3–0.8) plus, with p = 0.5, a burst: the link
stalls 0.2–1 s and flushes the buffered samples at 4× the rate (the first 1.4 s of every Rasteiro file);
stamps t_j = τ_j + d_j made increasing (a host never stamps two packets in the wrong order). Beyond a mean
delay of ~1 period, FIFO queueing bunches the stamps and the clock is no longer identified from them
(a 12 ms mean on a 10 ms clock: lock √N·C 3.4–4.0, period off by 7–50 %; 8 ms: lock 8.6–9.6, τ within
0.3 ms): such stamps are not injected.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import Correction, Effect, check_train, gyro_exact, noise_scale, replace_session
from imugraph.diagnose.sample_clock import fit_clock, robust_rms

RANGES = {"mean_delay_samples": (0.5, 1.0), "burst_p": 0.5, "burst_s": (0.2, 1.0)}
RELEVANT_SAMPLES = 1.0 / np.sqrt(12.0)   # relevance: robust RMS of the stamp deviation, sample periods
STAMPS_KEY = "timestamp_jitter_stamps"   # meta key: the original stamps of a re-timed session (refit)
SCREEN_REFIT = True          # (J6) the screening scores the refit θ* (the keyframes-fixed Δω cannot undo a base
                             # fit bent by the stamps: V1000 MPU9150 screened (A2) −1.32, refitted +0.88, §S20-T)
CHOOSE_BY_CLOSING = True     # (J7) between the starts' clocks, the one whose re-timed base fit closes best
MAX_SPREAD = 2.0             # (J7') a candidate clock needing a robust stamp spread > 2 samples is not chosen by (J7)
ENABLED = True               # DiagnoseOptions.timestamp_jitter (default since S20; run.load_effects drops it when False)


_CLOCK_CACHE: dict = {}
_REFIT_CACHE: dict = {}      # (real fit, θ*, info) of `TimestampJitter.refit`: screening and stage 2 share it
_CHOSEN: dict = {}           # (stamps, gyro) → the clock `refit` chose (J7)


def closing_error_deg(fit) -> float:
    """RMS over keyframe intervals of |ε_k|, ε_k = Σ_{j∈k} r_gyr,j Δt_j, degrees: the rotation by which the
    gyro integrated over an interval misses the next keyframe (with the samples between keyframes
    integrated from the gyro, (R1) spreads ε_k over the interval's samples as ε_k/(M Δt_j))."""
    kf = np.asarray(fit.keyframe_samples)
    dt = np.r_[np.diff(fit.session.t), 0.0]
    e = np.add.reduceat(np.nan_to_num(fit.residuals["gyr"]) * dt[:, None], kf[:-1], axis=0)   # [kf_k, kf_k+1)
    return float(np.degrees(np.sqrt(np.mean(np.sum(e**2, axis=1))))) if len(e) else 0.0


def _stamps_key(t: np.ndarray) -> tuple:
    return (len(t), hash(np.ascontiguousarray(t, float).tobytes()))


def _gyr_key(gyr) -> int | None:
    return None if gyr is None else hash(np.ascontiguousarray(gyr, float).tobytes())


def clock_candidates(t: np.ndarray) -> list:
    """`fit_clock(t, candidates=True)`, cached per stamp array (every fold and round: same stamps)."""
    key = _stamps_key(t)
    if key not in _CLOCK_CACHE:
        if len(_CLOCK_CACHE) >= 8:
            _CLOCK_CACHE.pop(next(iter(_CLOCK_CACHE)))
        _CLOCK_CACHE[key] = fit_clock(t, candidates=True)
    return _CLOCK_CACHE[key]


def clock_of(t: np.ndarray, gyr: np.ndarray | None = None) -> dict:
    """The clock of the stamps t: the one `TimestampJitter.refit` chose among the candidates (J7) for the
    recording with these stamps and this gyro once it ran, else `fit_clock(t)` (lowest (J3), cached)."""
    chosen = _CHOSEN.get((_stamps_key(t), _gyr_key(gyr)))
    return chosen if chosen is not None else clock_candidates(t)[0]


def clock_rate_change(t: np.ndarray, clock: dict) -> np.ndarray:
    """(N,) Δτ_j / Δt_j − 1 of (J2) (0 at the last sample and at non-increasing stamps)."""
    dt = np.diff(t)
    dtau = np.diff(clock["tau"])
    ratio = np.where(dt > 0, dtau / np.where(dt > 0, dt, 1.0), 1.0) - 1.0
    return np.r_[ratio, 0.0]


def retimed(session, clock: dict | None = None):
    """The session on its sample clock (J1): t ← τ − τ₀ (the refit θ*, the benchmark's evidence)."""
    c = clock or clock_of(session.t)
    return replace_session(session, t=c["tau"] - c["tau"][0], name_suffix="_retimed",
                           meta={"retimed": {"period_s": c["period"], "lost": c["lost"]}})


class JitterCorrection(Correction):
    """The gyro corrected by (J2) on the stamps' time base, residuals by exact re-integration; the gyro
    residual (R1) on the CLOCK's time base: the keyframe-mismatch rotation divided by the clock's
    durations, r_j = (y_j − δ_ω − ω̂'_j) = r_stamped,j · Δt_j / Δτ_j (J4) — on the stamps' base a burst
    of buffered samples (Δt = Δτ/4) would divide the same mismatch by a quarter of the time."""

    def raw_residuals(self, fit) -> dict:
        if self.deltas.get("of") is fit and "residuals" in self.deltas:        # (J6): the refit's residuals
            return {c: v.copy() for c, v in self.deltas["residuals"].items()}
        out = gyro_exact(fit, self.deltas["d_omega"])
        out["gyr"] = out["gyr"] / (1.0 + self.deltas["ratio"])[:, None]                  # (J4)
        return out

    def corrected(self, fit) -> dict:
        return {"gyr": fit.session.gyr + np.nan_to_num(np.asarray(self.deltas["d_omega"], float))}


class TimestampJitter(Effect):
    name = "timestamp_jitter"
    channel = "gyr"
    windowed = False
    ranges = RANGES

    @property
    def enabled(self) -> bool:
        """In the default library (`run.load_effects()`) only while ENABLED; a named request always has it."""
        return ENABLED

    def inject(self, session, rng, *, window=None, strength=None):
        """Stamp the samples on arrival: t'_j = t_j + d_j (module doc). strength: mean delay in sample
        periods (default uniform in RANGES); a burst (p = burst_p) in `window` or a random place."""
        period = float(np.median(session.dt))
        m = float(strength) if strength is not None else float(rng.uniform(*RANGES["mean_delay_samples"]))
        d = rng.exponential(m * period, session.n)                                  # receive delay
        burst = None
        if window is not None or rng.uniform() < RANGES["burst_p"]:
            b_len = float(rng.uniform(*RANGES["burst_s"]))
            a = int(np.searchsorted(session.t, window[0])) if window is not None \
                else int(rng.integers(0, max(1, session.n - int(b_len / period) - 1)))
            j = np.arange(a, session.n)
            stall = b_len - (j - a) * period * 0.75          # the link stalls b_len, then flushes at 4×
            d[j] = np.maximum(d[j], stall)
            burst = (float(session.t[a]), float(session.t[a] + b_len / 0.75))
        eps = 1e-4 * period * np.arange(session.n)           # FIFO: t'_j = max(t_j + d_j, t'_{j−1} + 10⁻⁴ Δ)
        t_new = np.maximum.accumulate(session.t + d - eps) + eps
        truth = {"params": {"mean_delay_samples": m, "burst": burst},
                 "t_start": None, "t_end": None}
        injected = {**session.meta.get("injected", {}), self.name: truth}
        return replace_session(session, t=t_new - t_new[0] + session.t[0], name_suffix="+timestamp_jitter",
                               meta={"injected": injected}), truth

    def fit(self, fit, train, window=None) -> Correction:
        """The sample clock from the stamps (J1)–(J3), (J7), then Δω of (J2) at the fit's bias. The clock's
        parameters use no residual (the stamps are another data stream); the choice between the two starts'
        clocks (J7) uses their re-timed fits on all samples, as θ* itself is fitted (the weak leak accepted
        in docs/diagnose.md §3); `train` only picks the samples of the noise re-estimation (rule 3)."""
        train = check_train(fit, train)
        s = fit.session
        stamps = s.meta.get(STAMPS_KEY)
        screen = SCREEN_REFIT and stamps is None and np.any(clock_rate_change(s.t, clock_of(s.t)))   # (J6)
        ext = self.refit(fit)[0] if screen else None   # (J7): the clock chosen among the candidates
        clock = clock_of(s.t if stamps is None else np.asarray(stamps, float), s.gyr)
        # on the refit θ* (`refit`) the session is already on the clock: nothing left to correct
        ratio = clock_rate_change(s.t, clock) if stamps is None else np.zeros(s.n)
        d_omega = (s.gyr - fit.b_gyr_bias) * ratio[:, None]                          # (J2)
        d_omega[~np.all(np.isfinite(d_omega), axis=1)] = 0.0
        dev = clock["deviation"]
        corr = JitterCorrection(self.name, {"period_s": clock["period"], "lost_samples": clock["lost"],
                                            "deviation_ms_p50_p99": [1e3 * float(np.median(dev)),
                                                                     1e3 * float(np.quantile(dev, 0.99))]},
                                n_params=2 + int(clock["lost"]), channel=self.channel,
                                deltas={"d_omega": d_omega, "clock": clock, "ratio": ratio})
        if screen and np.any(ratio):                                               # (J6)
            corr.deltas.update(of=fit, residuals={c: ext.residuals[c].copy() for c in ext.residuals})
        r = corr.raw_residuals(fit)
        corr.deltas["noise_scale"] = noise_scale(fit, r, train, ["acc", "mag"])
        return corr

    def refit(self, real, rounds: int = 2, window=None):
        """Full refit (docs/diagnose.md §3 (F1)) of the extended model: the base model fitted to the recording
        re-timed on its sample clock (J1) — the exact model, where the alternation on Δω of (J2) is not: Δω
        holds the base fit's bias δ_ω, biased by the stamps, and (y' − δ̂)Δt ≠ (y − δ)Δτ for any other bias.
        Started from the real fit (`fit_simulation`, its noise and rest), keyframes every as many samples as
        the base fit's (its stride), field on the gyro's time base as in `real.session`. Returns (θ* on the
        re-timed session, whose meta keeps the original stamps for `fit`/`size`, info)."""
        from dataclasses import replace as dc_replace

        from imugraph.diagnose.fit import base_options, fit_simulation

        key = (id(real), len(real.session.t), hash(np.ascontiguousarray(real.session.t).tobytes()),
               hash(np.ascontiguousarray(real.session.gyr).tobytes()))
        hit = _REFIT_CACHE.get(key)
        if hit is not None and hit[0] is real:
            return hit[1], dict(hit[2])
        def on_clock(clock):
            s_r = retimed(real.session, clock)
            s_r.meta[STAMPS_KEY] = real.session.t.copy()
            hz = float(real.info.get("keyframe_hz", 5.0)) * s_r.rate / real.session.rate     # same stride
            ext = fit_simulation(s_r, real, base_options(hz))
            ext.info["mag_delay_s"] = real.info.get("mag_delay_s", 0.0)
            return dc_replace(ext, info=dict(ext.info, keyframe_hz=real.info.get("keyframe_hz", 5.0)))

        cands = clock_candidates(real.session.t)
        fits = [on_clock(c) for c in cands]
        eps = [closing_error_deg(f) for f in fits]
        spread = [robust_rms(c) for c in cands]
        ok = [k for k in range(len(cands)) if spread[k] <= MAX_SPREAD or k == 0]          # (J7') plausible clocks
        if spread[0] < RELEVANT_SAMPLES:      # (J7''): stamps within a stamp's rounding of the (J3) clock ARE a clock
            ok = [0]                          # (lost samples only: x-IMU3's device stamps); the gyro's closing would
                                              # otherwise pick a period that stands in for a gyro scale error
        i = min(ok, key=lambda k: eps[k]) if CHOOSE_BY_CLOSING and len(ok) > 1 else 0      # (J7)
        clock, ext = cands[i], fits[i]
        if len(_CHOSEN) >= 8:
            _CHOSEN.pop(next(iter(_CHOSEN)))
        _CHOSEN[(_stamps_key(real.session.t), _gyr_key(real.session.gyr))] = clock
        info = {"rounds": [{"params": {"period_s": clock["period"], "lost_samples": clock["lost"]},
                            "t_start": None, "t_end": None}], "window": None, "changed": True,
                "stride": int(ext.info["stride"]),
                "candidates": [{"period_s": c["period"], "lost": c["lost"], "cost_J3": c["cost"],
                                "closing_deg": e, "spread_samples": r} for c, e, r in zip(cands, eps, spread)]}
        if len(_REFIT_CACHE) >= 2:
            _REFIT_CACHE.pop(next(iter(_REFIT_CACHE)))
        _REFIT_CACHE[key] = (real, ext, info)
        return ext, dict(info)

    def size(self, corr, fit) -> dict:
        """Robust RMS (1.4826·MAD) of the stamps' deviation from the clock, in sample periods (module doc),
        and the orientation error they cause over the keyframe intervals (RMS, degrees)."""
        c = corr.deltas["clock"]
        rms = robust_rms(c)
        stamps = np.asarray(fit.session.meta.get(STAMPS_KEY, fit.session.t), float)
        step = np.r_[np.diff(c["tau"]) - np.diff(stamps), 0.0]                       # Δτ_j − Δt_j
        dth = np.nan_to_num(fit.session.gyr - fit.b_gyr_bias) * step[:, None]
        kf = np.asarray(fit.keyframe_samples)
        per_int = np.add.reduceat(dth, kf[:-1], axis=0) if len(kf) > 1 else dth
        ang = float(np.degrees(np.sqrt(np.mean(np.sum(per_int**2, axis=1)))))
        return {"value": rms, "threshold": RELEVANT_SAMPLES, "unit": "samples (robust RMS of t − τ)",
                "orientation_error_deg_rms": ang}


EFFECT = TimestampJitter()
