"""The dip in DESIGN's convention, n_mag = [cos δ, 0, −sin δ] with x along the horizontal field: |δ| ≤ 90°.

The magnetometer model b_mag = D·bRn·n_mag(δ) + o is invariant under

    δ → π − δ,   nRb → Rz(π)·nRb            (n_mag(π − δ) = [−cos δ, 0, −sin δ] = Rz(π)·n_mag(δ))

(the nav frame turned by 180° about the vertical; gravity [0, 0, −g] is unchanged, D and o are body-frame). The
ML loop's δ is an unconstrained scalar, so from an initial δ₀ near 90° it can cross 90° and settle at the mirrored
optimum (U22 defect 1: the first 60 s of BROAD 06 from δ₀ = 82.4° to 109.9°; 21: 111.1°) — the same fit, but a
calibration.json whose x axis points against the horizontal field, which cpp_smoother's, cpp_field's and the stream's
initialisations (x along the horizontal field) do not expect (smooth --calibration 0.57° → 48.29°). This module folds
such a δ back and turns every nav-frame quantity with it, so the result is the same optimum in DESIGN's convention.
"""

from __future__ import annotations

import numpy as np


def folded_dip(dip_rad: float) -> tuple[float, bool]:
    """δ wrapped to (−π, π] and folded into [−π/2, π/2]: (δ', folded). folded: δ' = ±π − δ (the nav frame turned by
    Rz(π), `turn_quat` / `turn_vectors`); a δ already in [−π/2, π/2] is returned unchanged (bit-identical)."""
    dip = float(dip_rad)
    if -np.pi / 2 <= dip <= np.pi / 2 or not np.isfinite(dip):
        return dip, False
    wrapped = float(np.arctan2(np.sin(dip), np.cos(dip)))       # (−π, π]; n_mag is 2π-periodic in δ
    if -np.pi / 2 <= wrapped <= np.pi / 2:
        return wrapped, False
    return float(np.copysign(np.pi, wrapped) - wrapped), True   # π − δ (δ > 90°), −π − δ (δ < −90°)


def turn_quat(quat: np.ndarray) -> np.ndarray:
    """nRb → Rz(π)·nRb for (N, 4) w,x,y,z quaternions: q_z(π) ⊗ q with q_z(π) = (0, 0, 0, 1) gives (−z, −y, x, w)."""
    q = np.asarray(quat, float)
    return np.stack([-q[..., 3], -q[..., 2], q[..., 1], q[..., 0]], axis=-1)


def turn_vectors(v: np.ndarray | None) -> np.ndarray | None:
    """Nav-frame vectors (…, 3) → Rz(π)·v = (−x, −y, z); None stays None."""
    if v is None:
        return None
    out = np.array(v, float, copy=True)
    out[..., :2] *= -1.0
    return out


def folded_calibration(cal):
    """A Calibration with |dip| ≤ 90° (`folded_dip`): the same object when already so (bit-identical results), else a
    copy with δ' = ±180° − δ — the same magnetometer model in a nav frame turned by 180° about the vertical, in which
    orientations smoothed with it come out (a calibration.json written before this fold, or edited by hand)."""
    from dataclasses import replace

    dip, folded = folded_dip(np.deg2rad(cal.dip_deg))
    return replace(cal, dip_deg=float(np.rad2deg(dip))) if folded else cal
