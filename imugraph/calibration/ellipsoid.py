"""Ellipsoid fit of the raw magnetometer: Kok & Schön's initialisation, steps 1–2.

Kok, Hol, Schön, Gustafsson, Luinge (FUSION 2012), "Calibration of a magnetometer in combination with
inertial sensors", initial estimate, ellipsoid-fitting step: without disturbances the measurements lie
on an ellipsoid,

    ‖D⁻¹(y_t − o)‖² = 1   ⇔   y_tᵀ A y_t + bᵀ y_t + c = 0,   A = D⁻ᵀD⁻¹ ≻ 0            [ellipsoid]

which is linear in (A, b, c). The fit here solves that algebraic least-squares problem on data
normalised to zero mean and unit RMS radius (for numerical conditioning), takes the singular vector
of the smallest singular value as the quadric (‖θ‖ = 1 normalisation), checks that A is definite, and
returns the offset o₀ = −½A⁻¹b and the symmetric D₀ = (A/k)^(−½), k = o₀ᵀAo₀ − c. The ellipsoid only
fixes D up to an orthogonal factor (D₀Q for any Q with QᵀQ = I); `alignment.py` resolves that factor.

Identifiability (documented thresholds):
- at least `MIN_SAMPLES` valid rows;
- the design must have ONE near-null direction (the ellipsoid). Points on a plane or a circle
  (rotation about one axis) leave 4–5 null directions; a small cap of the sphere leaves a near-null
  second direction. We measure `design_cond` = σ_max / σ_2 of the design on normalised data
  (σ_2 the second-smallest singular value) and refuse above `MAX_DESIGN_COND`;
- the fitted axes must be plausible: longest/shortest axis ratio at most `MAX_AXIS_RATIO`
  (real soft-iron and scale errors stay well below 2:1; larger ratios come from fitting noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imugraph.errors import CalibrationError

MIN_SAMPLES = 20          # rows with a finite magnetometer sample (9 unknowns, with margin)
MAX_ROWS = 5000           # evenly spread subsample for speed
MAX_DESIGN_COND = 50.0    # σ_max / σ_2 of the normalised design; BROAD rotation trials: 5–12
MAX_AXIS_RATIO = 5.0      # longest / shortest ellipsoid semi-axis
INLIER_TOL = 0.06         # |‖D0⁻¹(y − o0)‖ − 1| of an inlier (undisturbed BROAD: RMS 0.02–0.03)
GOOD_INLIERS = 0.90       # accept the plain fit when this share of rows are inliers
MIN_INLIERS = 0.50        # a robust fit must explain at least this share of rows

_TOO_LITTLE = ("data hold too little rotation: the samples cover only part of the sphere "
               "(a plane, a single axis or a small cap); rotate the sensor about all three axes")


@dataclass
class EllipsoidFit:
    """Diagnostic record of one fit.

    Attributes:
        D0: (3, 3) symmetric positive-definite shape, magnetometer unit.
        o0: (3,) offset, magnetometer unit.
        design_cond: σ_max / σ_2 of the normalised design (see module docstring).
        axis_ratio: longest / shortest semi-axis.
        rms_norm_error: RMS of ‖D0⁻¹(y − o0)‖ − 1 over the rows used.
        n_used: rows used in the fit.
        inlier_fraction: share of the rows used within INLIER_TOL of the unit sphere.
    """

    D0: np.ndarray
    o0: np.ndarray
    design_cond: float
    axis_ratio: float
    rms_norm_error: float
    n_used: int
    inlier_fraction: float = 1.0


def _valid_rows(b_mag: np.ndarray, source: str) -> np.ndarray:
    """Finite rows of (N, 3) b_mag, subsampled evenly to at most MAX_ROWS."""
    b_mag = np.asarray(b_mag, float)
    if b_mag.ndim != 2 or b_mag.shape[1] != 3:
        raise CalibrationError(f"{source}: field 'mag': found shape {b_mag.shape}; expected (N, 3)")
    y = b_mag[np.all(np.isfinite(b_mag), axis=1)]
    if y.shape[0] < MIN_SAMPLES:
        raise CalibrationError(
            f"{source}: field 'mag': found {y.shape[0]} valid samples; expected at least "
            f"{MIN_SAMPLES} to fit the ellipsoid")
    if y.shape[0] > MAX_ROWS:
        y = y[np.linspace(0, y.shape[0] - 1, MAX_ROWS).round().astype(int)]
    return y


def _design(x: np.ndarray) -> np.ndarray:
    """(N, 3) normalised points → (N, 10) rows [x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z, 1]:
    [ellipsoid] is linear in θ = (A, g, j)."""
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    return np.stack([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c,
                     2 * a, 2 * b, 2 * c, np.ones_like(a)], axis=1)


def _solve_quadric(x: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Algebraic LS quadric through normalised points. Returns (A (3,3), g (3,), j, design_cond)
    for xᵀAx + 2gᵀx + j = 0."""
    _, s, Vt = np.linalg.svd(_design(x), full_matrices=False)      # min ‖Mθ‖ s.t. ‖θ‖ = 1
    design_cond = float(s[0] / max(s[-2], 1e-300))
    if design_cond > MAX_DESIGN_COND:
        raise CalibrationError(
            f"{source}: field 'mag': found an ill-conditioned ellipsoid fit (design condition "
            f"number {design_cond:.3g} > {MAX_DESIGN_COND:g}); expected samples spread over the "
            f"whole sphere: {_TOO_LITTLE}")
    th = Vt[-1]
    A = np.array([[th[0], th[3], th[4]], [th[3], th[1], th[5]], [th[4], th[5], th[2]]])
    return A, th[6:9], float(th[9]), design_cond


def _fit_rows(y: np.ndarray, source: str) -> EllipsoidFit:
    """The algebraic fit on (M, 3) finite rows (see `fit_ellipsoid_report`)."""
    if y.shape[0] < MIN_SAMPLES:
        raise CalibrationError(f"{source}: field 'mag': found {y.shape[0]} usable samples; expected "
                               f"at least {MIN_SAMPLES} to fit the ellipsoid")
    center = y.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((y - center) ** 2, axis=1))))
    if not scale > 0:
        raise CalibrationError(f"{source}: field 'mag': found a constant signal; expected a field "
                               f"that changes direction as the sensor rotates: {_TOO_LITTLE}")
    x = (y - center) / scale
    A, g, j, design_cond = _solve_quadric(x, source)
    if np.trace(A) < 0:
        A, g, j = -A, -g, -j
    eig = np.linalg.eigvalsh(A)
    x0 = -np.linalg.solve(A, g) if eig[0] > 0 else np.zeros(3)
    k = float(x0 @ A @ x0 - j)
    if eig[0] <= 0 or k <= 0:
        raise CalibrationError(
            f"{source}: field 'mag': found a quadric that is not an ellipsoid (eigenvalues of A "
            f"{np.array2string(eig, precision=3)}); expected a distorted sphere: {_TOO_LITTLE}, "
            f"or the field is disturbed")
    lam, V = np.linalg.eigh(A / k)                   # A/k = D0⁻ᵀD0⁻¹ in normalised units
    axis_ratio = float(np.sqrt(lam[-1] / lam[0]))
    if axis_ratio > MAX_AXIS_RATIO:
        raise CalibrationError(
            f"{source}: field 'mag': found an implausible ellipsoid (axis ratio {axis_ratio:.2f} > "
            f"{MAX_AXIS_RATIO}); expected a nearly spherical field: {_TOO_LITTLE}")
    D0 = scale * (V * lam ** -0.5) @ V.T             # symmetric square root, back to the raw unit
    o0 = center + scale * x0
    r = np.linalg.norm(np.linalg.solve(D0, (y - o0).T), axis=0) - 1.0
    return EllipsoidFit(D0, o0, design_cond, axis_ratio, float(np.sqrt(np.mean(r ** 2))), y.shape[0],
                        float(np.mean(np.abs(r) < INLIER_TOL)))


def _inliers(fit: EllipsoidFit, y: np.ndarray) -> np.ndarray:
    """(M,) bool: rows within INLIER_TOL of the fitted unit sphere."""
    return np.abs(np.linalg.norm(np.linalg.solve(fit.D0, (y - fit.o0).T), axis=0) - 1.0) < INLIER_TOL


def _window_fits(y: np.ndarray, source: str) -> list[EllipsoidFit]:
    """Fits on contiguous stretches (a quarter of the rows, half-overlapping) that succeed."""
    n = y.shape[0]
    size = n // 4
    fits = []
    for start in range(0, n - size + 1, max(1, size // 2)):     # 7 windows, not a per-sample loop
        try:
            fits.append(_fit_rows(y[start:start + size], source))
        except CalibrationError:
            continue
    return fits


def fit_ellipsoid_report(b_mag: np.ndarray, source: str = "<memory>",
                         robust: bool = True) -> EllipsoidFit:
    """Fit ‖D0⁻¹(y − o0)‖ ≈ 1 to the valid magnetometer rows, with diagnostics.

    Robust mode (against a field disturbed for part of the recording, e.g. a magnet attached for a
    minute): when fewer than GOOD_INLIERS of the rows lie within INLIER_TOL of the fitted sphere,
    fits on contiguous stretches are tried too; the fit with most inliers over ALL rows wins if they
    are at least MIN_INLIERS of them, and is refitted on its inliers.

    Args:
        b_mag: (N, 3) raw magnetometer, any unit; NaN rows are ignored.
        source: file name for error messages.
        robust: allow the inlier search above.

    Returns:
        EllipsoidFit with D0 (3, 3) symmetric positive definite and o0 (3,), both in the raw unit.

    Raises:
        CalibrationError: fewer than MIN_SAMPLES valid rows, the quadric is not an ellipsoid, or the
            fit is ill-conditioned (too little rotation); the message names the field 'mag'.
    """
    y = _valid_rows(b_mag, source)
    try:
        fits, error = [_fit_rows(y, source)], None
    except CalibrationError as err:
        fits, error = [], err
    if not robust or (fits and fits[0].inlier_fraction >= GOOD_INLIERS):
        if error is not None:
            raise error
        return fits[0]
    fits += _window_fits(y, source)
    scored = [(float(np.mean(_inliers(f, y))), i) for i, f in enumerate(fits)]
    if not scored or max(scored)[0] < MIN_INLIERS:
        if error is not None:
            raise error
        return fits[0]
    best = fits[max(scored)[1]]
    return _fit_rows(y[_inliers(best, y)], source)


def fit_ellipsoid(b_mag: np.ndarray, source: str = "<memory>") -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoid fit (Kok et al. 2012, [ellipsoid]): D0 symmetric, o0 so that ‖D0⁻¹(y − o0)‖ ≈ 1.

    Args:
        b_mag: (N, 3) raw magnetometer, any unit; NaN rows are ignored.
        source: file name for error messages.

    Returns:
        D0: (3, 3) symmetric positive definite, raw unit.
        o0: (3,) offset, raw unit.

    Raises:
        CalibrationError: see `fit_ellipsoid_report`.
    """
    fit = fit_ellipsoid_report(b_mag, source)
    return fit.D0, fit.o0
