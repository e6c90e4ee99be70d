"""An intermittent magnetic disturbance (S20-M, opt-in; docs/diagnose.md §S20-M): why and how
magnetic_disturbance searches several windows (M6, conditions in `MagneticDisturbance.find_windows` under the
flag `magnetic_disturbance.INTERMITTENT`, `DiagnoseOptions.magnet_intermittent`), and the code of (M7), a
window's field drifting through it (`drift_jacobian`, flag `VISIT_DRIFT`).

Why. A magnet lying at a fixed place (BROAD 28/30, "a small magnet placed in a stationary location") adds
a field that is a function of the sensor's POSITION, b_mag,j = D bRn,j (n_mag + Δn(p_j)) + o + e_m with
|Δn(p)| ∝ 1/|p − p_magnet|³ (a dipole). An IMU alone has no position, but the consequence in time is
plain: the field is there while the sensor is near the magnet and gone when it is not — SEVERAL windows,
one per visit, each with an (almost) constant field while the sensor rests or moves little near the magnet
((M1) per window). The default search (magnetic_disturbance.find_windows) was built for a magnet attached
to the sensor (one long window) and has two limits that drop visits:

  1. at most MAX_WINDOWS = 3 windows in all (step windows (M3') and excess-energy windows together);
  2. a step window that the (M3) test accepted is dropped when `refine_edge` moves its edges closer than
     STEP_MIN_S: BROAD 28's second visit (≈ 143.8–146.7 s at ≥ 0.1 |m|, 0.63 |m| in the base residual)
     was accepted by (M3') as 144.4–146.4 s (its minimum length, 8 blocks: 1.98 s from first to last sample)
     and dropped after the refinement had moved its start later (docs/diagnose.md §S20-M).

The search (M6) (`MagneticDisturbance.find_windows` with INTERMITTENT, MAX_VISITS):
  * (M3') up to MAX_VISITS windows (the χ² Bonferroni threshold and the floor 0.05 |m| are (M3)'s: each
    further window must pass the same test on the residual of the (M1) fit of those found before);
  * the excess-energy windows of the (M1) residual that overlap none of them, as before (min 2 s);
  * each window's edges refined to the step in the residual's mean (`refine_edge`); when the refinement
    leaves less than STEP_MIN_S the (M3) edges are kept (the test accepted that window with n_in ≥ L
    blocks; refinement only locates an edge within ±2 s, it is no evidence against the window).
No threshold is new: MAX_VISITS bounds the work (each window costs 6 columns of (M1)); every window must
pass (M3)'s test. Fields per window are fitted by (M1) as before (`_solve_fields`).
"""

from __future__ import annotations

import numpy as np

DRIFT_ORDER = 2              # (M7): Legendre orders 1..DRIFT_ORDER of each window's field


def drift_jacobian(fit, env: list, bRn: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(M7) Columns of a window field that changes smoothly through the window (opt-in:
    `magnetic_disturbance.VISIT_DRIFT`, `DiagnoseOptions.magnet_visit_drift`). A stationary magnet's field at
    the sensor, D bRn Δn(p) (module doc), is constant only while the sensor rests; during a visit the sensor
    (or the hand placing the magnet) moves a little and |Δn| ∝ 1/r³ follows. Per window w (envelope e_w,
    ramps (R1) included) the field of (M1) becomes

        e_w(t) Σ_{k=0..K} P_k(τ_w(t)) (Δo_w,k + D bRn Δn_w,k),   τ_w = 2 (t − a_w)/(b_w − a_w) − 1       (M7)

    (P_k Legendre, a_w..b_w the envelope's support); k = 0 is (M1)'s Δo_w, Δn_w, these are the columns of
    k = 1..DRIFT_ORDER (6 per order and window), appended after (M1)'s so its parameter layout stays. A
    magnet attached to the sensor (constant body field) needs none of them: the cross-validation pays their
    parameter cost. Measured on BROAD 28 (docs/diagnose.md §S20-M): held-out far WORSE (shrink 0.28 → 0.03, with
    (M6) −4.38): fitted on the training blocks of a 2–4 s window, the polynomial extrapolates into the held-out
    block inside it. Kept opt-in for the record. Returns (N, 3, 6·K·W)."""
    t = fit.session.t
    K = DRIFT_ORDER
    J = np.zeros((fit.n, 3, 6 * K * len(env)))
    for i, e_w in enumerate(env):
        m = e_w > 0
        if m.sum() < 2:
            continue
        a, b = float(t[m].min()), float(t[m].max())
        tau = 2.0 * (t[m] - a) / max(b - a, 1e-9) - 1.0
        DB = D @ bRn[m]                                                             # D bRn over the window
        for k in range(1, K + 1):
            P = np.polynomial.legendre.Legendre.basis(k)(tau) * e_w[m]
            c = 6 * (K * i + k - 1)
            J[m, :, c:c + 3] = P[:, None, None] * np.eye(3)                      # P_k Δo_w,k
            J[m, :, c + 3:c + 6] = P[:, None, None] * DB                          # P_k D bRn Δn_w,k
    return J


__all__ = ["DRIFT_ORDER", "drift_jacobian"]
