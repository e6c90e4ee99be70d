"""magnetic_disturbance: an extra magnetic field over a time window (a magnet attached to the sensor, or
the sensor held near a magnetised object).

Model, in window w (Kok & Schön's magnetometer model (B3) plus windowed terms):

    b_mag,j = D · bRn,j · (n_mag + Δn_w) + o + Δo_w + e_m,      j in w                           (M1)

Δo_w: body-frame field of a magnet fixed to the sensor (hard iron that moves with it); Δn_w: nav-frame
field of a nearby magnetised object (constant while the sensor stays close to it). The fit also re-estimates
the offset o by δo (the base fit's o was pulled by the disturbance). Linear in (δo, Δo_w, Δn_w) given the
fitted orientations: least squares on the training samples.

Windows: the `window` argument (the diagnosis' localisation), else found from the magnetometer residual of
all samples — moving mean of |r/σ|², flagged where well above its quiet level (base.detect_windows) — with
each edge refined to the step in the residual's mean (base.refine_edge). Only the window edges use the
held-out samples (localisation); the fields are estimated on training samples only.

Refit (imugraph.diagnose.refit): `corrected` leaves the windows' field samples out, so the refitted D, o,
dip and heading come from undisturbed samples.

Relevance (`size`): the window's extra field ≥ 10 % of |m| (M2). The heading comes from the horizontal
field |m| cos(dip), so at BROAD's dip (≈ 69°) 10 % of |m| can turn it by up to asin(0.1 / cos 69°) ≈ 16°
(not "~6°", which holds at dip 0). A heading-based threshold, sin 6° · cos(dip) (3.7 % of |m| on BROAD),
was tried: it flagged the clean BROAD 04 (a 0.061 |m| field over 31–38 s of its full length, (A2) 0.35 on
that window) and did not help 36 (its magnet is not significant: the joint refit makes the mag gap worse
there, docs/diagnose.md §5), so the 10 % rule stays.

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


class MagneticCorrection(Correction):
    """(M1) evaluated at every sample."""

    def corrected(self, fit) -> dict:
        """For the full refit: the magnetometer samples of the windows (widened by PAD_S) left out (NaN),
        so that the base refit's D, o, dip and heading come from undisturbed samples only — the limit of
        (M1) with a free field per sample in the window, which also covers a field that is not constant."""
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


class MagneticDisturbance(Effect):
    name = "magnetic_disturbance"
    channel = "mag"
    windowed = True
    ranges = RANGES
    joint_options = {"disturbance_windows": True}   # imugraph.calibration.disturbance: the same model (M1)

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
        masks = [(t >= a) & (t <= b) for a, b in windows]
        masks = [m for m in masks if np.any(m & use)]
        windows = [w for w, m in zip(windows, [(t >= a) & (t <= b) for a, b in windows]) if np.any(m & use)]
        n_col = 12 + 6 * len(masks)
        J = np.zeros((fit.n, 3, n_col))
        J[:, :, 0:3] = np.eye(3)                                              # δo
        b_n = bRn @ fit.calibration.n_mag
        for a in range(3):
            J[:, a, 3 + 3 * a:6 + 3 * a] = b_n                                # δD row a · bRn n_mag
        for i, m in enumerate(masks):
            c = 12 + 6 * i
            J[m, :, c:c + 3] = np.eye(3)                                      # Δo_w
            J[m, :, c + 3:c + 6] = D @ bRn[m]                                 # D bRn Δn_w
        w = 1.0 / np.asarray(fit.sigma["mag"], float)
        A = (J[use] * w[None, :, None]).reshape(-1, n_col)
        y = (r[use] * w).reshape(-1)
        ridge = 1e-6 * np.eye(n_col)                                          # Δo vs Δn without rotation
        theta = np.linalg.solve(A.T @ A + ridge * max(1.0, np.trace(A.T @ A) / n_col), A.T @ y)
        delta = np.einsum("nij,j->ni", J, theta)
        d_window = np.einsum("nij,j->ni", J[:, :, 12:], theta[12:])                  # Δo_w + D bRn Δn_w
        res = {c: fit.residuals[c].copy() for c in fit.residuals}
        res["mag"] = r - delta
        corr = MagneticCorrection(
            self.name, {"offset_change": theta[:3].tolist(),
                        "D_change": theta[3:12].reshape(3, 3).tolist(),
                        "windows": [{"t_start": a, "t_end": b, "body_offset": theta[12 + 6 * i:15 + 6 * i].tolist(),
                                     "nav_field": theta[15 + 6 * i:18 + 6 * i].tolist()}
                                    for i, (a, b) in enumerate(windows)]},
            n_params=n_col + 2 * len(windows),
            t_start=windows[0][0] if windows else None, t_end=windows[0][1] if windows else None,
            channel=self.channel, deltas={"mag": delta, "window": d_window})
        corr.deltas["noise_scale"] = noise_scale(fit, res, train, ["mag"])
        return corr

    def size(self, corr, fit) -> dict:
        """Largest window's extra field (median |Δo_w + D bRn Δn_w| over it) / median |D bRn n_mag|."""
        bRn = np.transpose(fit.nRb, (0, 2, 1))
        earth = float(np.median(np.linalg.norm((bRn @ fit.calibration.n_mag) @ np.asarray(fit.calibration.D).T,
                                               axis=1)))
        dw = np.linalg.norm(corr.deltas.get("window", np.zeros((fit.n, 3))), axis=1)
        best = 0.0
        for w in corr.params.get("windows", []):
            m = (fit.session.t >= w["t_start"]) & (fit.session.t <= w["t_end"])
            if m.any():
                best = max(best, float(np.median(dw[m])))
        return {"value": best / max(earth, 1e-12), "threshold": RELEVANT_FRACTION, "unit": "fraction of |m|"}

    @staticmethod
    def find_windows(fit) -> list:
        """Disturbance windows (t_start, t_end) from the magnetometer residual of all samples."""
        t = fit.session.t
        r = fit.residuals["mag"]
        z2 = np.sum((r / fit.sigma["mag"]) ** 2, axis=1) / 3.0
        found = detect_windows(t, z2, smooth_s=1.0, factor=4.0, min_s=2.0, merge_s=2.0)[:MAX_WINDOWS]
        half = max(3, int(round(2.0 * fit.session.rate)))
        out = []
        for i0, i1 in found:
            a = refine_edge(r, i0, half)
            b = refine_edge(r, i1 - 1, half)
            if b > a:
                out.append((float(t[a]), float(t[b])))
        return sorted(out, key=lambda w: -(w[1] - w[0]))


EFFECT = MagneticDisturbance()

__all__ = ["EFFECT", "MagneticDisturbance", "RANGES", "window_mask"]
