"""magnetic_disturbance: an extra magnetic field over a time window (a magnet attached to the sensor, or
the sensor held near a magnetised object).

Model, in window w (Kok & Schön's magnetometer model (B3) plus windowed terms):

    b_mag,j = D · bRn,j · (n_mag + Δn_w) + o + Δo_w + e_m,      j in w                           (M1)

Δo_w: body-frame field of a magnet fixed to the sensor (hard iron that moves with it); Δn_w: nav-frame
field of a nearby magnetised object (constant while the sensor stays close to it). The fit also re-estimates
the offset o by δo (the base fit's o was pulled by the disturbance). Linear in (δo, Δo_w, Δn_w) given the
fitted orientations: least squares on the training samples.

Windows: the `window` argument (the diagnosis' localisation), else found from the magnetometer residual of
all samples — steps of its mean (`step_windows`, (M3): a field fixed to the sensor), then windows where
the moving mean of |r/σ|² is well above its quiet level (base.detect_windows) that overlap none of them —
with each edge refined to the step in the residual's mean (base.refine_edge). Only the window edges use the
held-out samples (localisation); the fields are estimated on training samples only.

Refit (`MagneticDisturbance.refit`, the alternation of imugraph.diagnose.refit with the effect's own
windows): `FieldRemoved.corrected` removes the windows' fitted field from the measurements (and leaves the
ramps at their edges out), the base model is refitted to them, and the field is estimated again against
that fit. (`MagneticCorrection.corrected`, which leaves the windows' samples out, is no longer used by the
diagnosis.)

Ramped edges (S15, default `RAMPS` / `DiagnoseOptions.magnet_ramps`; effects/edge_ramps.py (R1)–(R2)): the
window's field switched on and off by linear ramps of fitted width instead of a step (a magnet brought by
hand); the windows' t_start/t_end are then the ramps' centres (docs/diagnose.md §S15).

Relevance (`size`): the window's extra field ≥ 10 % of |m| (M2). The heading comes from the horizontal
field |m| cos(dip), so at BROAD's dip (≈ 69°) 10 % of |m| can turn it by up to asin(0.1 / cos 69°) ≈ 16°
(not "~6°", which holds at dip 0). A heading-based threshold, sin 6° · cos(dip) (3.7 % of |m| on BROAD),
was tried: it flagged the clean BROAD 04 (a 0.061 |m| field over 31–38 s of its full length, (A2) 0.35 on
that window) and was not needed for 36 (0.129 |m| with the step windows (M3) and the refit by the effect's
own windows, docs/diagnose.md §3), so the 10 % rule stays.

Injection ranges (RANGES): field 10–60 µT-equivalent (≥ 20 % of a 50 µT field: above relevance) (scaled by the session's field magnitude / 50 µT),
uniformly random direction; window 15–40 % of the session; raised-cosine ramps 0.2–1.0 s (a magnet brought
by hand); mode "attached" (body frame, p = 1 by default) or "nearby" (nav frame, p = 1 − p_attached, needs
the orientation truth `quat`; off by default: a strong nav-frame field turns the fitted heading, which a
first-order refit cannot undo). Truth t_start / t_end: the ramps' mid-points.
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import (Correction, Effect, check_train, detect_windows, envelope,
                                             field_scale, noise_scale, random_window, refine_edge,
                                             replace_session, window_mask)
from imugraph.geometry import quat_to_rotmat

RANGES = {"field_uT": (10.0, 60.0), "window_frac": (0.15, 0.4), "ramp_s": (0.2, 1.0), "p_attached": 1.0}
MAX_WINDOWS = 3
PAD_S = 1.0                  # windows widened by this for the refit (the ramps of a magnet brought by hand)
RELEVANT_FRACTION = 0.10     # relevance: extra field ≥ 10 % of |m| (M2)
RAMPS = True                 # S15 (R1): the window's field with fitted linear ramps at its edges (default since S15)
STEP_REFIT = True            # S16-E (M3'): re-search windows on the residual of the (M1) fit of those found (default since S16)
INTERMITTENT = False         # S20-M (M6): several visits of a stationary magnet (find_windows; opt-in)
MAX_VISITS = 8               # (M6): windows at most (the (M3) test decides how many; this only bounds the work)
VISIT_DRIFT = False          # S20-M (M7): each window's field drifting through it (magnet_intermittent.drift_jacobian; opt-in)


class MagneticCorrection(Correction):
    """(M1) evaluated at every sample."""

    def corrected(self, fit) -> dict:
        """Data with the windows' magnetometer samples (widened by PAD_S) left out (NaN) — the limit of (M1)
        with a free field per sample in the window, which also covers a field that is not constant. Not
        what the diagnosis' refit uses (`FieldRemoved`, `MagneticDisturbance.refit`)."""
        t = fit.session.t
        wins = [(w["t_start"] - PAD_S, w["t_end"] + PAD_S) for w in self.params.get("windows", [])]
        if not wins:
            return {}
        mag = fit.session.mag.copy()
        mag[window_mask(t, wins)] = np.nan
        return {"mag": mag}

    def raw_residuals(self, fit) -> dict:
        out = {c: fit.residuals[c].copy() for c in fit.residuals}
        out["mag"] = out["mag"] - self.deltas["mag"]
        return out


class FieldRemoved(MagneticCorrection):
    """(M1) whose data-level correction removes the windows' fitted field (the diagnosis' refit)."""

    def corrected(self, fit) -> dict:
        """For the full refit: the windows' fitted extra field Δo_w + D bRn Δn_w removed from the
        magnetometer, y' = y − (Δo_w + D bRn Δn_w) (M1), and the samples within PAD_S of a window's edge
        left out (NaN: the ramps of a magnet brought by hand, which a constant field does not model).
        Leaving the whole windows out (the limit of (M1) with a free field per sample) was the rule before:
        it leaves the heading unobserved through a long window and D to the rotation outside it (BROAD 36,
        magnet over 35–98 s of a 44–130 s movement: D₂₁ 1.3 → 10.8, heading off by up to 16 µT of
        residual at rest), so the field is removed and the samples kept."""
        t = fit.session.t
        wins = self.params.get("windows", [])
        if not wins or "window" not in self.deltas:
            return {}
        mag = fit.session.mag - np.nan_to_num(self.deltas["window"])
        edges = [(w[k] - PAD_S, w[k] + PAD_S) for w in wins for k in ("t_start", "t_end")]
        mag[window_mask(t, edges)] = np.nan
        return {"mag": mag}


class MagneticDisturbance(Effect):
    name = "magnetic_disturbance"
    channel = "mag"
    windowed = True
    ranges = RANGES
    # imugraph.calibration.disturbance (windows from the field norm): what refit.refit_effect fits when
    # called on this effect directly; the diagnosis refits by `refit` (the effect's own windows)
    joint_options = {"disturbance_windows": True}
    correction = MagneticCorrection        # the Correction `fit` returns (FieldRemoved in `refit`)

    def inject(self, session, rng, *, window=None, strength=None):
        """Add (M1)'s field over a window. strength: field in µT-equivalent (default: random in range)."""
        F = field_scale(session)
        field_ut = float(strength) if strength is not None else float(rng.uniform(*RANGES["field_uT"]))
        window = tuple(window) if window is not None else random_window(session, rng, RANGES["window_frac"])
        ramp = float(rng.uniform(*RANGES["ramp_s"]))
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        vec = d * field_ut * F / 50.0
        has_truth = session.quat is not None and np.all(np.isfinite(session.quat))
        mode = "attached" if (rng.uniform() < RANGES["p_attached"] or not has_truth) else "nearby"
        env = envelope(session.t, window, ramp)
        if mode == "attached":
            extra = env[:, None] * vec                                        # Δo_w, body frame
        else:
            bRn = np.transpose(quat_to_rotmat(session.quat), (0, 2, 1))
            extra = env[:, None] * (bRn @ vec)                                # bRn Δn_w (D ≈ F·I)
        mag = session.mag + extra                                             # NaN rows stay NaN
        truth = {"params": {"mode": mode, "field_uT_equivalent": field_ut, "vector": vec.tolist(),
                            "ramp_s": ramp, "field_unit_scale": F},
                 "t_start": window[0], "t_end": window[1]}
        return replace_session(session, mag=mag, name_suffix="+magnetic_disturbance",
                               meta={"injected": {self.name: truth}}), truth

    def fit(self, fit, train, window=None) -> Correction:
        train = check_train(fit, train)
        t = fit.session.t
        r = fit.residuals["mag"]
        windows = [tuple(map(float, window))] if window is not None else self.find_windows(fit)
        valid = np.all(np.isfinite(r), axis=1)
        use = train & valid
        bRn = np.transpose(fit.nRb, (0, 2, 1))
        D = np.asarray(fit.calibration.D, float)
        steps = [((t >= a) & (t <= b)).astype(float) for a, b in windows]
        keep = [i for i, e in enumerate(steps) if np.any((e > 0) & use)]
        windows, env = [windows[i] for i in keep], [steps[i] for i in keep]
        edges = [None] * len(windows)
        theta, delta, d_window = _solve_fields(fit, r, use, bRn, D, env)
        if RAMPS and windows:                         # S15 (R1): the edges located as ramps (edge_ramps.py)
            from imugraph.diagnose.effects.edge_ramps import envelope as ramp_envelope, locate_ramps

            # located on the residual with the step model's δo, δD removed (the window's field kept): the
            # base fit's residual alone carries the offset and scale the magnet pulled (test_diagnose_s15)
            edges = locate_ramps(t, r - (delta - d_window), fit.sigma["mag"], windows)
            env = [ramp_envelope(t, e) for e in edges]
            windows = [(e["start"][0], e["end"][0]) for e in edges]           # the ramps' centres
            theta, delta, d_window = _solve_fields(fit, r, use, bRn, D, env)
        n_col = len(theta)
        res = {c: fit.residuals[c].copy() for c in fit.residuals}
        res["mag"] = r - delta
        corr = self.correction(
            self.name, {"offset_change": theta[:3].tolist(),
                        "D_change": theta[3:12].reshape(3, 3).tolist(),
                        "windows": [{"t_start": a, "t_end": b, "body_offset": theta[12 + 6 * i:15 + 6 * i].tolist(),
                                     "nav_field": theta[15 + 6 * i:18 + 6 * i].tolist(),
                                     **({} if edges[i] is None else {"ramp_start_s": edges[i]["start"][1],
                                                                     "ramp_end_s": edges[i]["end"][1]})}
                                    for i, (a, b) in enumerate(windows)]},
            n_params=n_col + 2 * len(windows) + 2 * sum(e is not None for e in edges),
            t_start=windows[0][0] if windows else None, t_end=windows[0][1] if windows else None,
            channel=self.channel, deltas={"mag": delta, "window": d_window})
        corr.deltas["noise_scale"] = noise_scale(fit, res, train, ["mag"])
        return corr

    def size(self, corr, fit) -> dict:
        """Largest window's extra field (median |Δo_w + D bRn Δn_w| over it) / median |D bRn n_mag|."""
        earth = earth_field_norm(fit)
        dw = np.linalg.norm(corr.deltas.get("window", np.zeros((fit.n, 3))), axis=1)
        best = 0.0
        for w in corr.params.get("windows", []):
            m = (fit.session.t >= w["t_start"]) & (fit.session.t <= w["t_end"])
            if m.any():
                best = max(best, float(np.median(dw[m])))
        return {"value": best / max(earth, 1e-12), "threshold": RELEVANT_FRACTION, "unit": "fraction of |m|"}

    def refit(self, real, rounds: int = 2, window=None):
        """Full refit (docs/diagnose.md §3 (F1)) of (M1) with the effect's OWN windows: the alternation of
        imugraph.diagnose.refit with the windows' fitted field removed from the data (`FieldRemoved.corrected`).
        The joint calibration (`joint_options`, imugraph.calibration.disturbance) finds its windows by the
        field norm, which a magnet weaker than ~15 % of |m| crosses only at some orientations (BROAD 36,
        0.12 |m|: 24 fragments over 36–127 s, half of them unmodelled, and a θ* whose gyro gap rose from 13
        to 23); the extended model must be base + THIS effect, so its windows are the effect's."""
        from imugraph.diagnose.refit import refit_effect

        return refit_effect(_ALTERNATION, real, rounds, window)

    @staticmethod
    def find_windows(fit) -> list:
        """Disturbance windows (t_start, t_end) from the magnetometer residual of all samples, longest
        first: steps of its mean (`step_windows`, (M3): a field fixed to the sensor), then windows of
        excess residual energy that overlap none of them (a field that is not constant in the body frame)."""
        t = fit.session.t
        r = fit.residuals["mag"]
        half = max(3, int(round(2.0 * fit.session.rate)))
        earth = earth_field_norm(fit)
        n_max = MAX_VISITS if INTERMITTENT else MAX_WINDOWS      # S20-M (M6): a stationary magnet's several visits
        if STEP_REFIT or INTERMITTENT:             # S16-E (M3'): each search after the (M1) fit of the windows found
            found, r_rest = step_windows_refit(fit, r, earth, max_windows=n_max)
        else:
            found, r_rest = [(i0, i1) for i0, i1, _, _ in step_windows(t, r, earth)], r
        n_step = len(found) if INTERMITTENT else 0                # (M6): a window (M3) accepted keeps its edges
        z2 = np.sum((r_rest / fit.sigma["mag"]) ** 2, axis=1) / 3.0
        for i0, i1 in detect_windows(t, z2, smooth_s=1.0, factor=4.0, min_s=2.0, merge_s=2.0):
            if all(i1 <= a or i0 >= b for a, b in found):
                found.append((i0, i1))
        out = []
        for k, (i0, i1) in enumerate(found[:n_max]):
            last = min(i1, len(t)) - 1
            a = refine_edge(r, i0, half)
            b = refine_edge(r, last, half)
            if t[b] - t[a] >= STEP_MIN_S:          # an edge refined onto the other: no window left ...
                out.append((float(t[a]), float(t[b])))
            elif k < n_step:                       # ... but (M6): a window (M3) accepted keeps its own edges
                out.append((float(t[i0]), float(t[last])))
        return sorted(out, key=lambda w: -(w[1] - w[0]))


def earth_field_norm(fit) -> float:
    """The undisturbed field's size in the magnetometer's units, median_j |D bRn,j n_mag| (the unit of (M3)'s
    0.05 |m| floor and of the relevance)."""
    bRn = np.transpose(fit.nRb, (0, 2, 1))
    return float(np.median(np.linalg.norm((bRn @ fit.calibration.n_mag) @ np.asarray(fit.calibration.D).T, axis=1)))


def _solve_fields(fit, r, use, bRn, D, env: list) -> tuple:
    """Least squares of (M1) on the samples `use`: δo, δD and per window (envelope e_w: 1 inside, 0 outside,
    ramps (R1) at the edges) e_w·Δo_w + e_w·D bRn Δn_w. Returns (θ, δ (N, 3) the whole change, the windows'
    field (N, 3))."""
    n_col = 12 + 6 * len(env)
    J = np.zeros((fit.n, 3, n_col))
    J[:, :, 0:3] = np.eye(3)                                              # δo
    b_n = bRn @ fit.calibration.n_mag
    for a in range(3):
        J[:, a, 3 + 3 * a:6 + 3 * a] = b_n                                # δD row a · bRn n_mag
    for i, e_w in enumerate(env):
        m = e_w > 0
        c = 12 + 6 * i
        e = e_w[m][:, None, None]                                         # 1 in the window; ramps (R1)
        J[m, :, c:c + 3] = e * np.eye(3)                                  # Δo_w
        J[m, :, c + 3:c + 6] = e * (D @ bRn[m])                           # D bRn Δn_w
    if VISIT_DRIFT and env:                   # S20-M (M7): each window's field drifting (Legendre), after (M1)'s columns
        from imugraph.diagnose.effects.magnet_intermittent import drift_jacobian

        J = np.concatenate([J, drift_jacobian(fit, env, bRn, D)], axis=2)
        n_col = J.shape[2]
    w = 1.0 / np.asarray(fit.sigma["mag"], float)
    A = (J[use] * w[None, :, None]).reshape(-1, n_col)
    y = (r[use] * w).reshape(-1)
    ridge = 1e-6 * np.eye(n_col)                                          # Δo vs Δn without rotation
    theta = np.linalg.solve(A.T @ A + ridge * max(1.0, np.trace(A.T @ A) / n_col), A.T @ y)
    delta = np.einsum("nij,j->ni", J, theta)
    d_window = np.einsum("nij,j->ni", J[:, :, 12:], theta[12:])                  # Δo_w + D bRn Δn_w
    return theta, delta, d_window


STEP_BLOCK_S = 0.25          # block length of the step search (longer for long recordings: ≤ STEP_MAX_BLOCKS)
STEP_MAX_BLOCKS = 800
STEP_MIN_S = 2.0             # shortest window (and shortest undisturbed remainder)
STEP_P = 0.01                # family-wise false-alarm probability of one step window on white residuals
STEP_FLOOR = 0.5 * RELEVANT_FRACTION   # smallest step kept, fraction of |m| (half the relevance)


def step_windows(t: np.ndarray, r: np.ndarray, field: float, max_windows: int = MAX_WINDOWS) -> list:
    """Windows where the mean of the magnetometer residual r (N, 3) steps away and back: a magnet attached
    to the sensor adds a constant body-frame field Δo_w (M1), which the base fit cannot follow (it splits
    it between o and the noise level: BROAD 36, a 5.6 µT magnet over 35–98 s, shows as ±2.7 µT around o
    and σ_z 2.4 µT, below the excess-energy detector's 4× quiet level).

    Square-wave ("epidemic") changepoint search on block means x_k (blocks of STEP_BLOCK_S, K blocks):
    for every window [a, b) of the blocks,

        LR(a, b) = n_in n_out / K · Σ_axis ((x̄_in − x̄_out) / s_axis)²                             (M3)

    the likelihood ratio of "one extra mean inside the window" against "one mean" for Gaussian block
    means of std s (robust, from first differences: s = 1.4826 MAD(Δx) / √2, insensitive to the steps
    themselves). Kept when LR exceeds the χ²₃ quantile at STEP_P / (K²/2) (Bonferroni over the windows:
    false alarm ≤ 1 % on white residuals) AND the step |x̄_in − x̄_out| ≥ STEP_FLOOR · |m| (colour of a real
    recording's residual makes LR large anyway; the difference of the two means is the window's field
    itself, whatever part of it the base fit's o absorbed, and a field below half the relevance threshold
    cannot become relevant). Greedy: the best window's step is removed and the search repeated.

    Returns [(i_start, i_stop, LR, step)] sample index ranges, in the order found."""
    from scipy.stats import chi2

    dur = float(t[-1] - t[0])
    rate = 1.0 / float(np.median(np.diff(t)))
    m = max(1, int(round(max(STEP_BLOCK_S, dur / STEP_MAX_BLOCKS) * rate)))
    K0 = len(t) // m
    xb = r[:K0 * m].reshape(K0, m, 3)
    ok = np.all(np.isfinite(xb), axis=2)
    cnt = ok.sum(1)
    mean = np.where(ok[:, :, None], xb, 0.0).sum(1) / np.maximum(cnt, 1)[:, None]
    idx = np.flatnonzero(cnt >= max(1, m // 2))
    x = mean[idx]
    K = len(x)
    L = max(2, int(round(STEP_MIN_S * rate / m)))
    if K < 4 * L:
        return []
    d = np.diff(x, axis=0)
    s = np.maximum(1.4826 * np.median(np.abs(d - np.median(d, 0)), 0) / np.sqrt(2), 1e-12)
    thr = float(chi2.isf(STEP_P / (K * K / 2.0), 3))
    a = np.arange(K + 1)
    n_in = (a[None, :] - a[:, None]).astype(float)                          # window [a, b) of blocks
    n_out = K - n_in
    valid = (n_in >= L) & (n_out >= L)
    # (M3) is symmetric between inside and outside: a window touching an end of the recording scores exactly as
    # its complement, and rounding chose (review R2: a 50–60.5 s magnet in 60 s reported as 0–50 s). The
    # disturbance is the shorter side: of two complements the longer one is not a window
    ends = (a[:, None] == 0) | (a[None, :] == K)
    valid &= ~(ends & (n_in > n_out))
    out = []
    y = x.copy()
    for _ in range(max_windows):
        P = np.vstack([np.zeros(3), np.cumsum(y, 0)])
        S = P[None, :, :] - P[:, None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            diff = S / n_in[..., None] - (P[-1] - S) / n_out[..., None]
            lr = np.where(valid, (n_in * n_out / K) * np.sum((diff / s) ** 2, axis=2), -np.inf)     # (M3)
        i, j = np.unravel_index(int(np.argmax(lr)), lr.shape)
        step = diff[i, j]
        if not (lr[i, j] > thr and np.linalg.norm(step) >= STEP_FLOOR * field):
            break
        out.append((int(idx[i] * m), int(min(len(t), idx[j - 1] * m + m)), float(lr[i, j]), step))
        y[i:j] -= step
    return out

def step_windows_refit(fit, r: np.ndarray, field: float, max_windows: int = MAX_WINDOWS) -> tuple:
    """(M3') The step search (M3) one window at a time, each time on the residual of the (M1) least-squares
    fit (δo, δD and the windows found so far, `_solve_fields`) instead of the residual with only the block
    means' step subtracted. Why: a strong magnet pulls the base fit's offset o and scale D (and the heading)
    over the whole recording; (M3)'s greedy removal of the window's mean leaves that pull in place, and its
    remainder — an orientation-dependent field δo + δD bRn n outside the window — shows as further "steps"
    (harness seed 1 case 001: a 0.90 |m| magnet at 120.7–130.7 s, then 0.07 |m| over 76.0–125.2 s, which
    became the reported window). Fitting (M1) first removes what the magnet pulled, so the next search sees
    only what (M1) with the windows found cannot explain. The thresholds are (M3)'s (χ² Bonferroni, floor).

    Returns ([(i_start, i_stop)], the residual r − δ of the last (M1) fit)."""
    t = fit.session.t
    bRn = np.transpose(fit.nRb, (0, 2, 1))
    D = np.asarray(fit.calibration.D, float)
    use = np.all(np.isfinite(r), axis=1)
    found, rest = [], r
    for _ in range(max_windows):
        sw = step_windows(t, rest, field, max_windows=1)
        if not sw or any(sw[0][0] < b and sw[0][1] > a for a, b in found):
            break                                          # nothing new (or the same window again)
        found.append(sw[0][:2])
        env = [((np.arange(len(t)) >= a) & (np.arange(len(t)) < b)).astype(float) for a, b in found]
        _, delta, _ = _solve_fields(fit, r, use, bRn, D, env)                  # (M1) on all windows found
        rest = r - delta
    return found, rest


EFFECT = MagneticDisturbance()


class _Alternation(MagneticDisturbance):
    """The effect as `MagneticDisturbance.refit` alternates it: no joint calibration, and corrections
    that remove the windows' field (`FieldRemoved`)."""

    joint_options = None
    correction = FieldRemoved


_ALTERNATION = _Alternation()

__all__ = ["EFFECT", "MagneticDisturbance", "RANGES", "step_windows", "step_windows_refit", "window_mask"]
