"""saturation: a channel clips at the sensor's measurement range.

Model: y_c,j,a = clip(h_c,a(x_j) + e, −L_c, +L_c): a sample at the rail only says |true value| ≥ L_c (a
censored measurement).                                                                                 (C1)

Fit: rails are found on all samples (a sensor property, like a window's location: one clipped episode
may lie in a held-out block) — per channel (gyr, acc) and axis, the extreme value (max or
min) repeated in runs of ≥ 2 consecutive samples, ≥ 3 times in all (a smooth signal almost never repeats
its extreme exactly; a clipped one sits on it). Correction at every sample whose value equals a rail:
acc rows are dropped (NaN: censored, (C1)); gyro peaks are reconstructed from a quadratic through the
`CONTEXT` unclipped samples on either side (never inside the rail), and the change Δω enters the first-
order refit (base (E1)–(E3)). One parameter (the level) per rail.

Significance (C2): a measurement with continuous-valued noise (the base model's white noise) repeats
its extreme EXACTLY in two separate episodes, each a run of ≥ 2 samples, with probability zero; a clipped
channel does it every time the motion exceeds the range. So the rail itself is the evidence
(`Correction.deltas["decisive"]`: the attribution counts it significant without a gap shrink): a clipped
gyro bends the fitted orientation only over the few keyframe intervals around each clipped peak, where
hand-held motion is fastest and the base model's misfit largest anyway, so the held-out gap shrink (even
on the support, attribution (A3)) was measured at 0.13–0.45 on BROAD 06 (2–3 % clipped). A sensor
quantised so coarsely that its peak value repeats in separate episodes would defeat (C2): not seen on
the floating-point outputs of BROAD (no rail found on the clean crops and trials diagnosed here).

Relevance (`size`): ≥ 5 samples on a rail.

Injection ranges (RANGES): the channel (gyr or acc, p = 0.5 each) clips on all axes at ±L, L chosen so
that 0.5–5 % of the samples exceed it on some axis (a range exceeded now and then by the fastest moves;
a level set as a fraction of the session's peak instead clipped a single 1-sample spike of BROAD 07's
accelerometer — 2 samples, nothing any diagnosis can see); the rail value is held exactly. The
accelerometer is only clipped when that level is ≥ 2 g (`acc_min_level`: no accelerometer's range is near
1 g), else the gyroscope is.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, gyro_exact, noise_scale,
                                             replace_session)
from imugraph.io.validate import runs

RANGES = {"clipped_frac": (0.005, 0.05), "channel_p": {"gyr": 0.5, "acc": 0.5}, "acc_min_level": 2.0 * 9.81}
CONTEXT = 6
MIN_RUN, MIN_COUNT = 2, 3
SUPPORT_S = 0.5             # the support of the attribution (A3): clipped samples ± 0.5 s (2.5 keyframe intervals)
MIN_EPISODES = 2             # (C2): the rail is reached in ≥ 2 separate episodes
MIN_CLIPPED = 5              # relevance: ≥ 5 samples on a rail (fewer is a chance repeat of a maximum)
CENSOR_GYRO = True           # S16-E (C1'): a gyro sample on a rail is censored in the residuals too (default since S16)
CENSOR_AREA = False           # S16-E (C1''): the censored gyro values estimated per keyframe interval (opt-in)


def on_rail(y: np.ndarray, level: float) -> np.ndarray:
    """Samples of y exactly at a rail `level` (to 1e-9 relative: a held value, not a nearby one)."""
    return np.abs(y - level) <= 1e-9 * max(1.0, abs(level))


def find_rails(y: np.ndarray, mask: np.ndarray) -> list:
    """[(axis, sign, level)] of the rails of y (N, 3) over the samples in mask (module doc)."""
    out = []
    for a in range(y.shape[1]):
        v = y[mask, a]
        v = v[np.isfinite(v)]
        if len(v) < 10:
            continue
        for sign, level in ((1.0, float(np.max(v))), (-1.0, float(np.min(v)))):
            hit = mask & on_rail(y[:, a], level)
            a0, a1 = runs(hit)
            if hit.sum() >= MIN_COUNT and np.any(a1 - a0 >= MIN_RUN):
                out.append((a, sign, level))
    return out


def reconstruct_peaks(t: np.ndarray, y: np.ndarray, rails: list) -> np.ndarray:
    """y with each clipped run replaced by a quadratic through its unclipped neighbours (never inside the
    rail)."""
    out = y.copy()
    for a, sign, level in rails:
        hit = on_rail(y[:, a], level)
        r0, r1 = runs(hit)
        for i0, i1 in zip(r0, r1):
            nb = np.r_[np.arange(max(0, i0 - CONTEXT), i0), np.arange(i1, min(len(y), i1 + CONTEXT))]
            nb = nb[~hit[nb]]
            if len(nb) < 3:
                continue
            tc = t[i0:i1].mean()
            coef = np.polyfit(t[nb] - tc, y[nb, a], 2)
            est = np.polyval(coef, t[i0:i1] - tc)
            out[i0:i1, a] = sign * np.maximum(sign * est, sign * level)
    return out


def censored_gyro(y: np.ndarray, y_new: np.ndarray, r: np.ndarray, rails: list) -> np.ndarray:
    """(C1') The gyro residual of a censored sample. A sample on a rail says only sign·ω ≥ sign·L (C1): its
    residual under the model is not y_new − ω̂ (the quadratic's guess minus the fit — a guess's error, many
    σ_ω: on the simulation of harness seed 1 case 011 the reconstruction is off by 0.014 rad/s RMS = 28 σ_ω,
    benchmarks/e5_saturation.py) but the violation of the inequality: none (NaN, as the accelerometer's
    censored rows) where the fitted rate is beyond the rail, L − ω̂ where it falls short of it (a fit that
    contradicts the measurement stays visible). r: residual against y_new; ω̂ = y_new − r."""
    out = r.copy()
    for a, sign, level in rails:
        hit = on_rail(y[:, a], level)
        pred = y_new[hit, a] - r[hit, a]                                   # the fit's ω̂ (incl. its bias)
        out[hit, a] = np.where(sign * (pred - level) >= 0.0, np.nan, level - pred)
    return out


def _rail_samples(y: np.ndarray, rails: list) -> list:
    """[(axis, sign, level, mask)] of the samples on each rail."""
    return [(a, sg, lv, on_rail(y[:, a], lv)) for a, sg, lv in rails]


def _intervals(fit) -> np.ndarray:
    """(N,) keyframe interval of each sample."""
    from imugraph.factors.gyro import keyframe_layout

    kf, _ = keyframe_layout(fit.n, int(fit.info["stride"]), fit.session.dt)
    return np.searchsorted(kf, np.arange(fit.n), side="right") - 1


def n_censored_intervals(fit, y: np.ndarray, rails: list) -> int:
    """Parameters of (C1''): one per (keyframe interval, rail) holding censored samples."""
    k_of = _intervals(fit)
    return int(sum(len(np.unique(k_of[m])) for _a, _s, _l, m in _rail_samples(y, rails)))


def censored_values(fit, y_new: np.ndarray, rails: list) -> np.ndarray:
    """(C1'') The censored gyro samples as unknowns ≥ the rail, estimated against the fit's keyframes.
    (C1) says a clipped sample only bounds the rate (sign·ω ≥ sign·L); the quadratic's guess (y_new) is off
    by many σ_ω (28 σ on the simulation of harness seed 1 case 011), and with the keyframes fixed the
    interval's integration mismatch spreads that error over every sample of the keyframe interval
    (`trajectory.reintegrate`: nRb_j = R_k Exp(u_j ε_k) ΔR_kj), where the unclipped samples' residual shows it
    (benchmarks/e5_saturation.py: 9.4 against the host's 2.1 whitened RMS in those intervals). One shift
    Δ_k per (interval, rail) of the censored samples (sign·Δ, i.e. further beyond the rail for Δ > 0):

        Δ_k = argmin Σ_{j in k, unclipped} |r_j + J_j Δ_k|²_Σ⁻¹ ,   subject to y_new + sign·Δ_k ≥ the rail       (C1'')

    J from one exact reintegration with every censored sample moved by sign·δ (the intervals decouple
    with the keyframes fixed; one reintegration per rail). Returns y_new with the shifts applied."""
    from imugraph.diagnose.effects.trajectory import gyro_exact

    s = fit.session
    k_of = _intervals(fit)
    w = 1.0 / np.asarray(fit.sigma["gyr"], float) ** 2
    y_out = y_new.copy()
    on = _rail_samples(s.gyr, rails)
    clipped = np.zeros(fit.n, bool)
    for _a, _sg, _lv, m in on:
        clipped |= m
    delta = 1e-3
    for a, sign, level, m in on:
        if not m.any():
            continue
        r0 = gyro_exact(fit, y_out - s.gyr)["gyr"]
        pert = y_out.copy()
        pert[m, a] += sign * delta
        J = (gyro_exact(fit, pert - s.gyr)["gyr"] - r0) / delta
        for k in np.unique(k_of[m]):
            iv = (k_of == k) & ~clipped & np.all(np.isfinite(r0), axis=1) & np.all(np.isfinite(J), axis=1)
            jj = float(np.sum(w * J[iv] ** 2))
            if jj <= 0.0:
                continue
            d_k = -float(np.sum(w * J[iv] * r0[iv])) / jj
            mk = m & (k_of == k)
            lb = -float(np.min(sign * (y_out[mk, a] - level)))      # stays at or beyond the rail
            y_out[mk, a] += sign * max(d_k, lb)
    return y_out


def separate_runs(y: np.ndarray, level: float, t: np.ndarray, gap_s: float = 0.1) -> int:
    """Number of separate episodes (runs of ≥ MIN_RUN samples at exactly `level`, more than `gap_s`
    apart) of one axis."""
    a0, a1 = runs(on_rail(y, level))
    keep = [(i0, i1) for i0, i1 in zip(a0, a1) if i1 - i0 >= MIN_RUN]
    n, last = 0, -np.inf
    for i0, i1 in keep:
        if t[i0] - last > gap_s:
            n += 1
        last = t[i1 - 1]
    return n


def clipped_support(s, rails: dict) -> np.ndarray:
    """(N,) bool: samples within SUPPORT_S of a sample on a rail — what the effect claims (attribution
    (A3)): a clipped gyro bends the fitted orientation over the keyframe intervals around it."""
    hit = np.zeros(s.n, bool)
    for c, rr in rails.items():
        y = getattr(s, c)
        for a, _sign, level in rr:
            hit |= on_rail(y[:, a], level)
    half = max(1, int(round(SUPPORT_S * s.rate)))
    return np.convolve(hit.astype(float), np.ones(2 * half + 1), "same") > 0


class SaturationCorrection(Correction):
    def raw_residuals(self, fit) -> dict:
        s = fit.session
        out = {c: fit.residuals[c].copy() for c in fit.residuals}
        rails = self.deltas["rails"]
        if rails.get("gyr"):
            y_new = reconstruct_peaks(s.t, s.gyr, rails["gyr"])
            area, censor = self.deltas["censor"]      # the module flags at fit time (run.model_switches)
            if area:
                y_new = censored_values(fit, y_new, rails["gyr"])
            out = gyro_exact(fit, y_new - s.gyr)
            if censor:
                out["gyr"] = censored_gyro(s.gyr, y_new, out["gyr"], rails["gyr"])
        for a, sign, level in rails.get("acc", []):
            out["acc"][on_rail(s.acc[:, a], level)] = np.nan                                  # censored
        return out


class Saturation(Effect):
    name = "saturation"
    channel = "gyr"
    windowed = False
    ranges = RANGES

    def inject(self, session, rng, *, window=None, strength=None):
        """Clip one channel at ±L. strength: the fraction of samples beyond the rail (default random in
        RANGES["clipped_frac"]); L is the matching quantile of the channel's largest |axis value|."""
        frac = float(strength) if strength is not None else float(rng.uniform(*RANGES["clipped_frac"]))
        names, p = zip(*RANGES["channel_p"].items())
        c = str(rng.choice(names, p=p))
        peak = np.nanmax(np.abs(session.acc), axis=1)
        if c == "acc" and np.nanquantile(peak, 1.0 - frac) < RANGES["acc_min_level"]:
            c = "gyr"                                                           # no accelerometer clips at 1 g
        y = getattr(session, c)
        level = float(np.nanquantile(np.nanmax(np.abs(y), axis=1), 1.0 - frac))
        clipped = np.clip(y, -level, level)
        truth = {"params": {"channel": c, "level": level, "level_frac": level / float(np.nanmax(np.abs(y))),
                            "clipped_fraction": float(np.mean(np.any(np.abs(y) > level, axis=1)))},
                 "t_start": None, "t_end": None}
        return replace_session(session, **{c: clipped}, name_suffix="+saturation",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        train = check_train(fit, train)
        s = fit.session
        rails = {c: find_rails(getattr(s, c), np.ones(fit.n, bool)) for c in ("gyr", "acc")}
        n_rails = sum(len(v) for v in rails.values())
        channel = "acc" if rails["acc"] and not rails["gyr"] else "gyr"
        params = {"rails": {c: [{"axis": a, "sign": sg, "level": lv} for a, sg, lv in v] for c, v in rails.items()},
                  "channel": channel}
        corr = SaturationCorrection(self.name, params, n_params=n_rails, channel=channel,
                                    deltas={"rails": rails, "censor": (CENSOR_AREA, CENSOR_GYRO)})
        if rails["gyr"]:
            y_new = reconstruct_peaks(s.t, s.gyr, rails["gyr"])
            if CENSOR_AREA:                                     # (C1''): the refit's data carry the estimate
                y_new = censored_values(fit, y_new, rails["gyr"])
                corr.n_params += n_censored_intervals(fit, s.gyr, rails["gyr"])
            corr.deltas["d_omega"] = y_new - s.gyr
        if n_rails:
            corr.deltas["support"] = clipped_support(s, rails)
            corr.deltas["decisive"] = any(separate_runs(getattr(s, c)[:, a], lv, s.t) >= MIN_EPISODES
                                          for c, rr in rails.items() for a, _sg, lv in rr)          # (C2)
            changed = ["gyr", "acc", "mag"] if rails["gyr"] else ["acc"]
            corr.deltas["noise_scale"] = noise_scale(fit, corr.raw_residuals(fit), train, changed)
        return corr


    def size(self, corr, fit) -> dict:
        """Number of samples on a rail (relevance ≥ MIN_CLIPPED)."""
        s = fit.session
        n = 0
        for c, rails in corr.deltas.get("rails", {}).items():
            y = getattr(s, c)
            for a, _sign, level in rails:
                n += int(np.sum(on_rail(y[:, a], level)))
        return {"value": float(n), "threshold": float(MIN_CLIPPED), "unit": "clipped samples"}


EFFECT = Saturation()
