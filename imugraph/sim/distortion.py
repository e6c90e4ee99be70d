"""Random linear magnetometer distortions y' = A y + b (the "distorted BROAD" experiment).

A distortion applied to a magnetometer that already follows b_mag = D·bRn·n_mag + o (Kok & Schön)
gives another one of the same model:

    A (D bRn n_mag + o) + b = (A D) bRn n_mag + (A o + b),   so  D' = A D,  o' = A o + b.      (1)

`random_distortion` draws A = S · K · Mᵀ (each row of A is one sensing axis: its gain times its unit
direction in the inertial sensor axes):

    S = diag(s_x, s_y, s_z)        per-axis scale, s_i ~ U[0.75, 1.3]
    K = [[1,     0,            0          ],
         [sin a, cos a,        0          ],
         [sin b, cos b sin c,  cos b cos c]]   non-orthogonal unit axes, a, b, c ~ U[−6°, 6°]
    M = Exp(φ u)                   misalignment: u uniform on the sphere, φ ~ U[0°, 6°]
    b_i ~ U[−1.2, 1.2] · field_norm  offset per axis

so that the documented ranges can be checked on A itself: the row norms are s_i, the angles between
normalised rows are 90° − a, 90° − b and 90° − asin(sin a sin b + cos a cos b sin c), and
M = (K⁻¹ S⁻¹ A)ᵀ is a rotation of at most 6°.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import expmap
from imugraph.io.session import Session

_SOURCE = "<imugraph.sim.distortion>"


def skew_axes(a: float, b: float, c: float) -> np.ndarray:
    """(3, 3) K: rows are unit sensing axes with non-orthogonality angles a, b, c (rad), see module doc."""
    return np.array([
        [1.0, 0.0, 0.0],
        [np.sin(a), np.cos(a), 0.0],
        [np.sin(b), np.cos(b) * np.sin(c), np.cos(b) * np.cos(c)],
    ])


def random_distortion(
    rng: np.random.Generator,
    field_norm: float,
    *,
    scale_range: tuple[float, float] = (0.75, 1.3),
    max_skew_deg: float = 6.0,
    max_misalign_deg: float = 6.0,
    max_offset: float = 1.2,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw a random magnetometer distortion A = S·K·Mᵀ and offset b (ranges in the module doc).

    Args:
        rng: random generator.
        field_norm: |field| in the magnetometer's unit; offsets scale with it.
        scale_range: (low, high) of the per-axis scale s_i.
        max_skew_deg: bound of each non-orthogonality angle a, b, c, degrees.
        max_misalign_deg: bound of the misalignment rotation angle φ, degrees.
        max_offset: bound of each offset component, in units of field_norm.

    Returns:
        A: (3, 3) distortion matrix (dimensionless).
        b: (3,) offset, magnetometer unit, each |b_i| ≤ max_offset · field_norm.

    Raises:
        SessionError: non-positive field_norm or an empty scale range.
    """
    if not (np.isfinite(field_norm) and field_norm > 0):
        raise SessionError(_SOURCE, "field_norm", str(field_norm), "a positive finite number")
    lo, hi = scale_range
    if not (0 < lo <= hi):
        raise SessionError(_SOURCE, "scale_range", str(scale_range), "0 < low ≤ high")
    S = np.diag(rng.uniform(lo, hi, 3))
    a, b_ang, c = np.deg2rad(rng.uniform(-max_skew_deg, max_skew_deg, 3))
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    phi = np.deg2rad(rng.uniform(0.0, max_misalign_deg))
    M = expmap(phi * axis)
    A = S @ skew_axes(a, b_ang, c) @ M.T
    b = rng.uniform(-max_offset, max_offset, 3) * field_norm
    return A, b


def apply_distortion(b_mag: np.ndarray, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """y' = A y + b for every row, eq. (1); NaN rows (no magnetometer sample) stay NaN.

    Args:
        b_mag: (N, 3) magnetometer samples, any unit.
        A: (3, 3) distortion.
        b: (3,) offset, same unit as b_mag.

    Returns:
        (N, 3) new array (the input is not modified).

    Raises:
        SessionError: wrong shapes.
    """
    y = np.asarray(b_mag, float)
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    if y.ndim != 2 or y.shape[1] != 3:
        raise SessionError(_SOURCE, "b_mag", f"shape {y.shape}", "(N, 3)")
    if A.shape != (3, 3) or b.shape != (3,):
        raise SessionError(_SOURCE, "A/b", f"shapes {A.shape}/{b.shape}", "(3, 3) and (3,)")
    out = y @ A.T + b
    out[~np.all(np.isfinite(y), axis=1)] = np.nan
    return out


def distort_session(session: Session, A: np.ndarray, b: np.ndarray) -> Session:
    """A new Session whose magnetometer is A·mag + b; the input session is left untouched.

    If the input's magnetometer follows (D, o), the output follows (A D, A o + b), eq. (1). The
    distortion is recorded in meta["distortion"] = {"A": 3×3 list, "b": 3 list}.

    Args:
        session: the source session (not modified).
        A: (3, 3) distortion.
        b: (3,) offset in the session's magnetometer unit.

    Returns:
        Session sharing t/gyr/acc/quat/movement with the input (read-only use) and a new mag.

    Raises:
        SessionError: wrong shapes.
    """
    mag = apply_distortion(session.mag, A, b)
    meta = dict(session.meta)
    meta["distortion"] = {"A": np.asarray(A, float).tolist(), "b": np.asarray(b, float).tolist()}
    return dataclasses.replace(session, mag=mag, meta=meta, name=f"{session.name}_distorted")
