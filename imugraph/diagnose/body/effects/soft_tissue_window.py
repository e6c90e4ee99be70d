"""soft_tissue over a time window (option `BodyDiagnoseOptions.soft_tissue_window`; docs/diagnose_body.md,
"Session 22, helper D22").

Why: the soft_tissue fit (soft_tissue.py, (ST6)) fits one set of gains over the whole recording, while a tissue
can wobble only part of the time (a strap loosening; the harness injects a 30–70 % window in half of its cases).
A global fit then (i) shrinks the gains towards the window's share (the size, RMS of d over the WHOLE recording,
falls below the 1 mm floor: Xsens-17 LeftShoulder, injected 2.3 mm in its window, fitted 0.35 mm) and (ii)
predicts a wobble in the held-out blocks outside the window, so one fold's log-score gain turns negative and
the sign test fails (CMU LeftFoot: folds +4.1, +3.6, −2.7, +4.3, +19.8). Both harness misses of session 18 were
windowed injections: the model, not the rule, lacked the window.

Model: the (ST6) columns switched on inside a window W = [t_a, t_b) only,

    Δjacc_i = −1_W(t_i) (d̈_i + 2 ω_i × ḋ_i + ω̇_i × d_i + ω_i × (ω_i × d_i)),     d = Σ_a c_a x_a e_a      (SW1)

(every channel's rows by their own time base: samples for jacc, keyframe-interval starts for the keyframe
channels against a refit θ*), W on a grid of WINDOW_STEP_S = 1 s edges, at least MIN_WINDOW_S = 2 s long,
the whole recording included. For each (ω_n, ζ) of the soft_tissue grid and each W the gains are least squares
on the whitened training rows; with per-bin sums of AᵀA, Aᵀy, yᵀy (bins of 1 s) every window costs one 3×3
solve:

    cost(W) = yᵀy − (A_Wᵀy)ᵀ (A_WᵀA_W)⁻¹ (A_Wᵀy)                                                   (SW2)

and the (ω_n, ζ, W) of least training cost is the fit. Parameters: 3 gains + ω_n, ζ + t_a, t_b = 7 (the BIC
cost of (A4') grows accordingly). Size: RMS of the fitted d INSIDE W (the tissue's displacement where it moves;
the injection's truth is measured the same way). The correction (deltas, residuals) is the windowed one.
(SW3): the window is chosen once on all rows, the gains per fold inside it ((SW5), option value "shape": and
(ω_n, ζ) too, only the gains per fold); (SW4): the sign test (A4'') over
the folds with held-out samples inside the window (run.score_candidate, this option only).
"""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.body.effects.base import BodyCorrection
from imugraph.diagnose.body.effects.soft_tissue import GRID_F_HZ, GRID_ZETA, RELEVANT_M, SoftTissue
from imugraph.diagnose.body.fit import CHANNELS

WINDOW_STEP_S = 1.0
MIN_WINDOW_S = 2.0


def _bin_sums(base: dict, cols: list, sigma: dict, train: dict, bins: dict, n_bins: int):
    """Per-bin AᵀA (B, 3, 3), Aᵀy (B, 3), yᵀy (B,) of the whitened training rows (SW2)."""
    AtA = np.zeros((n_bins, 3, 3))
    Aty = np.zeros((n_bins, 3))
    yty = np.zeros(n_bins)
    for c in CHANNELS:
        if base[c].shape[1] == 0:
            continue
        ok = train[c] & np.all(np.isfinite(base[c]), axis=1)
        s = np.asarray(sigma[c], float)
        y = base[c][ok] / s                                                   # (n, d)
        A = np.stack([col[c][ok] / s for col in cols], axis=2)               # (n, d, 3)
        b = bins[c][ok]
        np.add.at(AtA, b, np.einsum("ndp,ndq->npq", A, A))
        np.add.at(Aty, b, np.einsum("ndp,nd->np", A, y))
        np.add.at(yty, b, np.sum(y * y, axis=1))
    return AtA, Aty, yty


def windows(n_bins: int, step: float, min_len: float) -> np.ndarray:
    """(W, 2) bin ranges [i, j) of the candidate windows (SW1), the whole recording first."""
    m = max(1, int(np.ceil(min_len / step - 1e-9)))
    out = [(0, n_bins)] + [(i, j) for i in range(n_bins) for j in range(i + m, n_bins + 1) if (i, j) != (0, n_bins)]
    return np.array(out, int)


class WindowedSoftTissue(SoftTissue):
    """soft_tissue with the window (SW1) fitted (module doc); same name, injection and columns."""

    window_sign_test = True                  # (SW4) in run.score_candidate
    fix_shape = False                        # (SW5): (ω_n, ζ) also from all rows, only the gains per fold

    def search(self, bfit, sensor, train, sigma, fixed=None, grid=None):
        """(f_n, ζ, θ, (i, j) bins) of least training cost (SW2); fixed: a window (i, j) to keep; grid: the
        (f_n, ζ) pairs to try (None: the soft_tissue grid)."""
        sf = bfit.sensors[sensor]
        base = sf.residuals
        t = np.asarray(bfit.session.t, float)
        n_bins = max(1, int(np.ceil((t[-1] - t[0]) / WINDOW_STEP_S + 1e-9)))
        bins = {c: np.clip(((sf.time_base(c) - t[0]) / WINDOW_STEP_S).astype(int), 0, n_bins - 1) for c in CHANNELS}
        W = windows(n_bins, WINDOW_STEP_S, MIN_WINDOW_S) if fixed is None else np.array([fixed], int)
        cache = bfit.info.setdefault("_soft_tissue_columns", {})
        best = None
        for f_n, zeta in (grid or [(f, z) for f in GRID_F_HZ for z in GRID_ZETA]):
            key = (sensor, f_n, zeta)
            if key not in cache:
                cache[key] = self.columns(bfit, sensor, f_n, zeta)
            cols, _ = cache[key]
            AtA, Aty, yty = _bin_sums(base, cols, sigma, train, bins, n_bins)
            P_AA = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(AtA, axis=0)])
            P_Ay = np.concatenate([np.zeros((1, 3)), np.cumsum(Aty, axis=0)])
            AA = P_AA[W[:, 1]] - P_AA[W[:, 0]]
            Ay = P_Ay[W[:, 1]] - P_Ay[W[:, 0]]
            scale = np.sqrt(np.maximum(np.einsum("wii->wi", AA), 1e-300))          # column scaling
            AAs = AA / scale[:, :, None] / scale[:, None, :] + 1e-12 * np.eye(3)
            th_s = np.linalg.solve(AAs, -(Ay / scale)[..., None])[..., 0]
            red = -np.einsum("wi,wi->w", th_s, Ay / scale)                       # (SW2): yᵀy − cost
            w = int(np.argmax(red))
            cost = float(yty.sum() - red[w])
            if best is None or cost < best[0]:
                best = (cost, f_n, zeta, th_s[w] / scale[w], (int(W[w][0]), int(W[w][1])))
        return best[1:], bins, n_bins

    def fit(self, bfit, sensor, train, sigma) -> BodyCorrection:
        """(SW1)–(SW2). The window is chosen ONCE on all rows of the fit (cached per fit and sensor: (SW3), a weak
        leak of two parameters into the held-out blocks, as stage 2's θ*), the gains and (ω_n, ζ) per call on
        `train` inside it: a window searched per fold on 2 s-interleaved training rows moved from fold to fold
        (measured, docs: folds −2.2 … +4.2 on a found 7–11 s window)."""
        key = (sensor, id(bfit.sensors[sensor]), id(bfit.session.sensors[sensor]))
        wcache = bfit.info.setdefault("_soft_tissue_window", {})
        if key not in wcache:
            every = {c: np.ones(r.shape[0], bool) for c, r in bfit.sensors[sensor].residuals.items()}
            wcache[key] = self.search(bfit, sensor, every, sigma)[0]
        f0, z0, _, w0 = wcache[key]
        (f_n, zeta, theta, (i, j)), bins, n_bins = self.search(bfit, sensor, train, sigma, fixed=w0,
                                                               grid=[(f0, z0)] if self.fix_shape else None)
        sf = bfit.sensors[sensor]
        base = sf.residuals
        t = np.asarray(bfit.session.t, float)
        cols, (ds, dacc) = bfit.info["_soft_tissue_columns"][(sensor, f_n, zeta)]
        t_a, t_b = float(t[0]) + i * WINDOW_STEP_S, min(float(t[0]) + j * WINDOW_STEP_S, float(t[-1]))
        on = {c: ((bins[c] >= i) & (bins[c] < j)).astype(float)[:, None] for c in CHANNELS}
        res = {c: base[c] + on[c] * sum(th * col[c] for th, col in zip(theta, cols)) for c in CHANNELS}
        in_w = on["jacc"][:, 0] > 0
        d = sum(th * di for th, di in zip(theta, ds))
        rms = float(np.sqrt(np.mean(np.sum(d[in_w] ** 2, axis=1)))) if in_w.any() else 0.0
        whole = (i, j) == (0, n_bins)
        params = {"f_n_hz": f_n, "zeta": zeta, "translation_gain_m_per_g": theta.tolist(), "displacement_rms_m": rms,
                  "window_s": [t_a, t_b], "whole_recording": bool(whole)}
        return BodyCorrection(self.name, sensor, params, 7, self.channel, res,
                              t_start=None if whole else t_a, t_end=None if whole else t_b,
                              size={"value": rms, "threshold": RELEVANT_M, "unit": "m"},
                              deltas={"acc": on["jacc"] * sum(th * da for th, da in zip(theta, dacc))})


def folds_in_window(sf, folds: list, t_start, t_end, min_s: float = WINDOW_STEP_S) -> list:
    """(SW4) which folds hold at least `min_s` seconds of held-out samples (jacc time base) inside the fitted
    window: a fold whose held-out blocks all lie outside it cannot show the effect (its correction is zero
    there), so the sign test (A4'') runs over these folds only; all folds for a whole-recording fit."""
    if t_start is None:
        return [True] * len(folds)
    tb = sf.time_base("jacc")
    dt = float(np.median(np.diff(tb))) if tb.size > 1 else 1.0
    inside = (tb >= t_start) & (tb < t_end)
    need = max(1, int(round(min_s / dt)))                   # samples (a float sum of dt missed exactly 1 s)
    return [bool(np.sum(test["jacc"] & inside) >= need) for _, test in folds]


class WindowedSoftTissueShape(WindowedSoftTissue):
    """(SW5): the window AND (ω_n, ζ) chosen once on all rows, only the 3 gains per fold (a fold whose held-out
    blocks cover most of the window keeps little of it to choose a resonance from: measured, docs)."""

    fix_shape = True


EFFECT = WindowedSoftTissue()
EFFECT_SHAPE = WindowedSoftTissueShape()
