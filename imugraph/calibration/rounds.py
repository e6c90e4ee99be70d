"""Helpers of the ML rounds (imugraph.calibration.ml.ml_rounds): which field samples a round's solve and its
noise re-estimate see.

Kok & Schön's step 2 alternates the MAP solve with the ML noise levels from that solve's residuals. The two
must see the same samples: a magnetometer sample the solve leaves out (weight 0, e.g. inside a disturbance
window that its hard-iron offset does not explain, imugraph.calibration.disturbance) has no likelihood term,
so its residual carries no information about Σm. Counting it anyway (robust kernel weight only) leaked the
magnet's 58 µT into σ_mag,z on BROAD 32 (0.7 → 6.6–8.8 µT); the inflated σ then made the window look
"explained" (residual ≤ 3 σ), the next solve took it in, σ shrank again, the window flipped back to
unexplained: the rounds cycled with a period of 5 and ran to max_outer (Options.noise_skip_excluded).

fit_windows: each round's windowed hard-iron fit, with the verdict judged against σ_mag (fit_offsets) or on a
solve with the window modelled against that solve's undisturbed residual (Options.window_trial_verdict) — the latter
only when the rows outside the windows identify D by themselves (identified_without_windows).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from imugraph.calibration.disturbance import field_residuals, fit_offsets, fit_offsets_on_trial, robust_scale
from imugraph.graphs.measurements import MeasurementBlock


def solved_samples_block(block: MeasurementBlock) -> MeasurementBlock:
    """The block with the magnetometer rows of fixed weight 0 (left out of the solve) removed, for the noise
    re-estimate; the block itself when no row is left out. The remaining rows keep their weights, so

        σ_m,axis² = Σ_j w_j f_j ê_j,axis² / (Σ_j w_j f_j − p_m / 3)       (noise.reestimate, f_j the fixed weight)

    is the ML variance over exactly the samples in the solve's likelihood (rows with f_j = 0 add 0 to both sums
    in the solve's normal equations, and their information share p_m is already 0)."""
    ch = block.mag
    if ch is None or ch.weight_floor is None:
        return block
    keep = np.asarray(ch.weight_floor) > 0
    if keep.all():
        return block
    mag = replace(ch, kf=ch.kf[keep], kRb=ch.kRb[keep], values=ch.values[keep], weight_floor=ch.weight_floor[keep])
    return replace(block, mag=mag if keep.any() else None, _last={})


def thinned(y: np.ndarray, every: int) -> np.ndarray:
    """Every `every`-th field sample kept (NaN elsewhere): the ML rounds only steer the noise levels,
    bias and θ toward the final solve, which uses every sample."""
    if every <= 1:
        return y
    out = np.full_like(y, np.nan)
    idx = np.flatnonzero(np.all(np.isfinite(y), axis=1))[::every]
    out[idx] = y[idx]
    return out


def undisturbed_rms(windows: list, b_mag: np.ndarray, nRk: np.ndarray, pre, D: np.ndarray, o: np.ndarray,
                    n_nav: np.ndarray) -> float:
    """Robust residual scale (disturbance.robust_scale, per axis, raw unit) of the field samples outside every
    disturbance window at the solve's per-sample orientations (keyframes nRk interpolated as in the final
    output) of r_j = y_j − D bRn_j n_j − o, j undisturbed — the same formula as the windows' residual."""
    from imugraph.geometry import quat_to_rotmat
    from imugraph.graphs.orientation_init import sample_orientations

    out = np.all(np.isfinite(b_mag), axis=1)
    for w in windows:
        out[w.start:w.stop] = False
    if not out.any():
        return float("nan")
    nRb = quat_to_rotmat(sample_orientations(nRk, pre)[out])
    r = field_residuals(b_mag[out], nRb, D, o, n_nav if np.ndim(n_nav) == 1 else n_nav[out])
    return robust_scale(r)


def identified_without_windows(windows: list, session) -> bool:
    """Whether the field samples outside every disturbance window identify D by themselves: the coverage check
    (coverage.MAG_MIN_SPREAD) on the rows a solve keeps if it leaves every window out. The trial verdict may leave
    a window out for good (its first fit runs at orientations solved without it); when the rest does not identify
    D, D drifts (BROAD 34's first 67 s: spread 0.011 without its magnet windows, D's singular values 76, 45, 4.7;
    benchmarks/b_window_short.py), so those windows keep the σ_mag verdict (fit_offsets), which models them."""
    from imugraph.calibration.coverage import MAG_MIN_SPREAD, mag_spread_of_rows

    used = np.ones(len(session.t), bool)       # the windows are detected once: the answer is the same every round
    for w in windows:
        used[w.start:w.stop] = False
    return mag_spread_of_rows(session, used) >= MAG_MIN_SPREAD


def fit_windows(windows: list, opt, session, nRk: np.ndarray, pre, D: np.ndarray, o: np.ndarray, n_nav: np.ndarray,
                nRb: np.ndarray, sigma_mag: float) -> float:
    """One round's windowed hard-iron fit at the solve's orientations (nRb: per sample inside the windows).
    Returns a convergence 'change' for the rounds: inf while a window waits to be judged on the next solve
    (Options.window_trial_verdict), else 0. With that option, a recording whose rows outside the windows do not
    identify D keeps the σ_mag verdict (identified_without_windows): leaving its windows out would leave D free."""
    if not opt.window_trial_verdict or not identified_without_windows(windows, session):
        fit_offsets(windows, session.t, session.mag, nRb, D, o, n_nav, sigma_mag, opt.freeze_window_decision)
        return 0.0
    pending = fit_offsets_on_trial(windows, session.t, session.mag, nRb, D, o, n_nav,
                                   lambda: undisturbed_rms(windows, session.mag, nRk, pre, D, o, n_nav))
    return float("inf") if pending else 0.0
