"""Scoring estimated orientations against truth (the metric of the BROAD benchmark comparisons).

The score of an estimate nRb_est against a reference nRb_ref (both body → nav, quaternions w,x,y,z) is the
RMS over the scored samples of the total rotation angle between them,

    θ_k = ∠( nRb_ref,k · (Rz(ψ) · nRb_est(k + s))ᵀ ),                                   (1)

taken at the constant heading offset ψ (a rotation about nav z, applied on the left of the estimate) and the
time shift s (samples, fractional, estimate resampled by slerp) that make it smallest. ψ is removed because
the heading reference of an estimator (magnetic north in its own frame) and of the truth (optical frame)
differ by a constant; s is searched within ±max_shift samples in shift_step steps because the IMU and
optical clocks differ by ≈ 1.25 samples on BROAD and estimators time-stamp an integrated gyro step
differently (see ../shared/data/README.md, "Facts measured on BROAD").

Sign of the shift: `shift_samples = s` means the estimate is compared at index k + s with the reference at
index k, i.e. a positive s says the estimate lags the reference by s samples.

Samples are scored where the mask is true, the reference is finite (BROAD's `opt_quat` is NaN where the
optical tracking dropped) and the estimate is finite on every sample the shift search can touch. The first
and last ceil(max_shift) + 1 samples are never scored, so every shift is scored on the same samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.optimize import minimize_scalar

from imugraph.errors import ImugraphError

_REFINE_BOUND_RAD = np.deg2rad(10.0)  # search half-width around the closed-form heading offset
_REFINE_TOP = 3  # shifts whose heading offset is refined by the 1-D minimisation


class EvaluationError(ImugraphError):
    """The arrays handed to a metric cannot be scored (shape, no finite samples)."""

    def __init__(self, field: str, found: str, expected: str):
        self.field, self.found, self.expected = field, found, expected
        super().__init__(f"imugraph.evaluate: argument '{field}': found {found}; expected {expected}")


@dataclass(frozen=True)
class OrientationScore:
    """An orientation error summary in degrees.

    Attributes:
        rms_deg: RMS of the per-sample error angle, degrees.
        mean_deg: mean of the per-sample error angle, degrees.
        max_deg: largest per-sample error angle, degrees.
        shift_samples: time shift s of the estimate that scored best (positive: estimate lags), samples.
        heading_offset_deg: heading offset ψ removed, nRb_ref ≈ Rz(ψ)·nRb_est, degrees in (−180, 180].
        n: number of samples scored.
        shift_s: the same shift in seconds (shift_samples / rate_hz).
    """

    rms_deg: float
    mean_deg: float
    max_deg: float
    shift_samples: float
    heading_offset_deg: float
    n: int
    shift_s: float = 0.0


@dataclass(frozen=True)
class _Alignment:
    """The best shift and heading offset and the aligned error quaternions q'_k = q_ref ⊗ (rz ⊗ q_est,s)*."""

    shift: float
    psi: float
    q_err: np.ndarray  # (4, K) component-major w,x,y,z, nav frame
    idx: np.ndarray    # (K,) the scored sample indices (_scored_index)


def _check_quats(name: str, q: np.ndarray, n: Optional[int]) -> np.ndarray:
    q = np.asarray(q, float)
    if q.ndim != 2 or q.shape[1] != 4 or (n is not None and q.shape[0] != n):
        want = f"shape (N, 4){'' if n is None else f' with N = {n}'}"
        raise EvaluationError(name, f"shape {q.shape}", want)
    return q


def _qmul_conj(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """p ⊗ q* for (4, K) component-major arrays (Hamilton product with the conjugate of q)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.stack([
        pw * qw + px * qx + py * qy + pz * qz,
        -pw * qx + px * qw - py * qz + pz * qy,
        -pw * qy + px * qz + py * qw - pz * qx,
        -pw * qz - px * qy + py * qx + pz * qw,
    ])


def shift_quat(quat: np.ndarray, index: np.ndarray, shift: float) -> np.ndarray:
    """Orientation at fractional sample positions index + shift, by slerp between neighbouring samples.

    Args:
        quat: (N, 4) unit quaternions w,x,y,z.
        index: (K,) integer sample indices; index + shift must lie within [0, N − 1].
        shift: fractional shift in samples.

    Returns:
        (K, 4) interpolated unit quaternions.
    """
    return _shift_cm(np.ascontiguousarray(np.asarray(quat, float).T), index, shift).T


def _shift_cm(quat_cm: np.ndarray, index: np.ndarray, shift: float) -> np.ndarray:
    """`shift_quat` on a (4, N) component-major array, returning (4, K)."""
    base = int(np.floor(shift))
    u = shift - base
    q0 = quat_cm[:, index + base]
    return q0 if u < 1e-12 else _slerp_cm(q0, quat_cm[:, index + base + 1], u)


def _slerp_cm(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Slerp q0 → q1 at fraction u for (4, M) component-major unit quaternions (shortest path)."""
    d = np.einsum("ik,ik->k", q0, q1)
    q1 = q1 * np.where(d < 0.0, -1.0, 1.0)
    th = np.arccos(np.minimum(np.abs(d), 1.0))
    small = th < 1e-6
    s = np.sin(np.where(small, 1.0, th))
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * th) / s)
    w1 = np.where(small, u, np.sin(u * th) / s)
    q = w0 * q0 + w1 * q1
    return q / np.sqrt(np.einsum("ik,ik->k", q, q))


def _shifted_estimates(est_cm: np.ndarray, index: np.ndarray, shifts: np.ndarray):
    """Yield (s, (4, K) estimate at index + s) for each shift, slerping each fractional part only once."""
    between: dict[float, np.ndarray] = {}  # fractional part u → slerp of every neighbouring pair at u
    for s in shifts:
        base = int(np.floor(s + 1e-9))
        u = round(float(s) - base, 9)
        if u == 0.0:
            yield float(s), est_cm[:, index + base]
            continue
        if u not in between:
            between[u] = _slerp_cm(est_cm[:, :-1], est_cm[:, 1:], u)
        yield float(s), between[u][:, index + base]


def _remove_heading(q_err: np.ndarray, psi: float) -> np.ndarray:
    """q_err ⊗ rz(ψ)*, i.e. the error once the estimate is pre-multiplied by Rz(ψ) (eq. 1)."""
    c, s = np.cos(0.5 * psi), np.sin(0.5 * psi)
    w, x, y, z = q_err
    return np.stack([w * c + z * s, x * c - y * s, x * s + y * c, z * c - w * s])


def _angles(q_err: np.ndarray) -> np.ndarray:
    """(K,) rotation angle in rad of each error quaternion, 2·atan2(|v|, |w|) (accurate for small angles)."""
    w, x, y, z = q_err
    return 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), np.abs(w))


def _closed_form_psi(q_err: np.ndarray) -> float:
    """Heading offset maximising Σ⟨q_err,k, rz(ψ)⟩² (the chordal mean of the heading differences).

    With v = (cos ψ/2, sin ψ/2) and the 2×2 scatter S of (w_k, z_k), vᵀSv is largest at
    ψ = atan2(2 S_wz, S_ww − S_zz).
    """
    w, z = q_err[0], q_err[3]
    # einsum, not np.dot: a threaded BLAS call costs tens of ms on a busy 2-core machine
    s_wz, s_ww, s_zz = (np.einsum("k,k->", a, b) for a, b in ((w, z), (w, w), (z, z)))
    return float(np.arctan2(2.0 * s_wz, s_ww - s_zz))


def _rms_at(q_err: np.ndarray, psi: float) -> float:
    return float(np.sqrt(np.mean(_angles(_remove_heading(q_err, psi)) ** 2)))


def _scored_index(quat_est: np.ndarray, quat_ref: np.ndarray, mask: Optional[np.ndarray],
                  margin: int) -> np.ndarray:
    """(K,) indices scored: mask, finite reference, finite estimate within ±margin, away from the ends."""
    n = quat_ref.shape[0]
    keep = np.ones(n, bool) if mask is None else np.asarray(mask, bool).reshape(-1)
    if keep.shape[0] != n:
        raise EvaluationError("mask", f"length {keep.shape[0]}", f"length {n} (one flag per sample)")
    bad_est = (~np.all(np.isfinite(quat_est), axis=1)).astype(float)
    near_bad = np.convolve(bad_est, np.ones(2 * margin + 1), mode="same") > 0
    keep = keep & np.all(np.isfinite(quat_ref), axis=1) & ~near_bad
    keep[:margin] = False
    keep[n - margin:] = False
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        raise EvaluationError("mask", "no sample that is masked in, finite in both and away from the ends",
                              "at least one scorable sample")
    return idx


def _align(quat_est: np.ndarray, quat_ref: np.ndarray, mask: Optional[np.ndarray], max_shift: float,
           shift_step: float, heading: bool) -> _Alignment:
    """Find the shift s and heading offset ψ minimising the RMS of eq. (1)."""
    quat_ref = _check_quats("quat_ref", quat_ref, None)
    quat_est = _check_quats("quat_est", quat_est, quat_ref.shape[0])
    if shift_step <= 0 or max_shift < 0:
        raise EvaluationError("shift_step/max_shift", f"{shift_step}/{max_shift}", "step > 0 and max ≥ 0")
    margin = int(np.ceil(max_shift)) + 1
    idx = _scored_index(quat_est, quat_ref, mask, margin)
    q_ref = np.ascontiguousarray((quat_ref[idx] / np.linalg.norm(quat_ref[idx], axis=1, keepdims=True)).T)
    est = np.ascontiguousarray((quat_est / np.linalg.norm(quat_est, axis=1, keepdims=True)).T)
    n_steps = int(np.floor(max_shift / shift_step + 1e-9))
    shifts = shift_step * np.arange(-n_steps, n_steps + 1)
    cands = []
    for s, est_s in _shifted_estimates(est, idx, shifts):  # vectorised, one pass per shift (25 by default)
        q_err = _qmul_conj(q_ref, est_s)
        psi = _closed_form_psi(q_err) if heading else 0.0
        cands.append((_rms_at(q_err, psi), float(s), psi, q_err))
    cands.sort(key=lambda c: c[0])
    if heading:  # the RMS optimum is not closed-form: refine ψ on the best few shifts (bounded 1-D search)
        refined = []
        for _, s, psi0, q_err in cands[:_REFINE_TOP]:
            res = minimize_scalar(lambda p: _rms_at(q_err, p), method="bounded", options={"xatol": 1e-9},
                                  bounds=(psi0 - _REFINE_BOUND_RAD, psi0 + _REFINE_BOUND_RAD))
            psi = float(res.x) if res.fun < _rms_at(q_err, psi0) else psi0
            refined.append((_rms_at(q_err, psi), s, psi, q_err))
        cands = sorted(refined, key=lambda c: c[0])
    _, s, psi, q_err = cands[0]
    psi = float(np.angle(np.exp(1j * psi)))
    return _Alignment(shift=s, psi=psi, q_err=_remove_heading(q_err, psi), idx=idx)  # (4, K)


def _score(angles_rad: np.ndarray, al: _Alignment, rate_hz: float) -> OrientationScore:
    a = np.rad2deg(np.abs(angles_rad))
    return OrientationScore(
        rms_deg=float(np.sqrt(np.mean(a**2))), mean_deg=float(np.mean(a)), max_deg=float(np.max(a)),
        shift_samples=al.shift, heading_offset_deg=float(np.rad2deg(al.psi)), n=int(a.size),
        shift_s=float(al.shift / rate_hz),
    )


def orientation_error(quat_est: np.ndarray, quat_ref: np.ndarray, mask: Optional[np.ndarray],
                      rate_hz: float, *, max_shift: float = 3.0, shift_step: float = 0.25,
                      heading: bool = True) -> OrientationScore:
    """Total orientation error (eq. 1) at the best time shift and best constant heading offset.

    Args:
        quat_est: (N, 4) estimated nRb, w,x,y,z (body → nav).
        quat_ref: (N, 4) reference nRb, w,x,y,z; NaN rows are ignored.
        mask: (N,) bool samples to score (e.g. BROAD `movement`), or None for all.
        rate_hz: sampling rate in Hz (only to report the shift in seconds).
        max_shift: largest |time shift| searched, samples.
        shift_step: shift grid step, samples.
        heading: remove the best constant heading offset (False: ψ = 0).

    Returns:
        OrientationScore of the total rotation angle, degrees.

    Raises:
        EvaluationError: wrong shapes or no scorable sample.
    """
    al = _align(quat_est, quat_ref, mask, max_shift, shift_step, heading)
    return _score(_angles(al.q_err), al, rate_hz)


def orientation_error_series(quat_est: np.ndarray, quat_ref: np.ndarray, mask: Optional[np.ndarray],
                             *, max_shift: float = 3.0, shift_step: float = 0.25,
                             heading: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The per-sample total angle of eq. (1) at the alignment `orientation_error` chooses (for plots over time):
    (idx, angle_deg), the scored sample indices (K,) and their error angles in degrees (K,)."""
    al = _align(quat_est, quat_ref, mask, max_shift, shift_step, heading)
    return al.idx, np.rad2deg(np.abs(_angles(al.q_err)))


def heading_error(quat_est: np.ndarray, quat_ref: np.ndarray, mask: Optional[np.ndarray],
                  rate_hz: float, *, max_shift: float = 3.0, shift_step: float = 0.25,
                  heading: bool = True) -> OrientationScore:
    """Heading part of the error at the alignment (shift, ψ) that minimises the total error.

    The aligned nav-frame error q' is split as q' = q_heading ⊗ q_incl with q_heading about nav z and
    q_incl about a horizontal axis; the heading error is 2·atan2(q'_z, q'_w), wrapped to (−π, π].

    Args:
        quat_est, quat_ref, mask, rate_hz, max_shift, shift_step, heading: as `orientation_error`.

    Returns:
        OrientationScore of |heading error|, degrees.

    Raises:
        EvaluationError: wrong shapes or no scorable sample.
    """
    al = _align(quat_est, quat_ref, mask, max_shift, shift_step, heading)
    w, z = al.q_err[0], al.q_err[3]
    sign = np.where(w < 0, -1.0, 1.0)
    return _score(2.0 * np.arctan2(sign * z, sign * w), al, rate_hz)


def inclination_error(quat_est: np.ndarray, quat_ref: np.ndarray, mask: Optional[np.ndarray],
                      rate_hz: float, *, max_shift: float = 3.0, shift_step: float = 0.25) -> OrientationScore:
    """Angle between the estimated and reference up-axes (heading-free), at the best time shift.

    Equals the angle of q_incl in `heading_error`'s split: 2·atan2(√(x'² + y'²), √(w'² + z'²)), which is
    the angle between nRb_estᵀ e_z and nRb_refᵀ e_z (the up-axis seen in the body frame).

    Args:
        quat_est, quat_ref, mask, rate_hz, max_shift, shift_step: as `orientation_error`.

    Returns:
        OrientationScore of the inclination error, degrees (heading_offset_deg is the ψ of the alignment).

    Raises:
        EvaluationError: wrong shapes or no scorable sample.
    """
    al = _align(quat_est, quat_ref, mask, max_shift, shift_step, True)
    w, x, y, z = al.q_err
    return _score(2.0 * np.arctan2(np.hypot(x, y), np.hypot(w, z)), al, rate_hz)


def field_norm_error(b_mag_cal: np.ndarray, valid: Optional[np.ndarray] = None) -> float:
    """RMS relative error of the calibrated field norm against 1: √mean((|b_mag_cal,k| − 1)²).

    Args:
        b_mag_cal: (N, 3) calibrated magnetometer field D⁻¹(b_mag − o), unit norm when calibrated.
        valid: (N,) bool rows to score (e.g. `Session.mag_valid`), or None; NaN rows are always skipped.

    Returns:
        RMS of |b_mag_cal| − 1 (dimensionless; 0.01 = 1 %).

    Raises:
        EvaluationError: wrong shape or no finite row.
    """
    b_mag_cal = np.asarray(b_mag_cal, float)
    if b_mag_cal.ndim != 2 or b_mag_cal.shape[1] != 3:
        raise EvaluationError("b_mag_cal", f"shape {b_mag_cal.shape}", "shape (N, 3)")
    keep = np.all(np.isfinite(b_mag_cal), axis=1)
    if valid is not None:
        keep &= np.asarray(valid, bool).reshape(-1)
    if not np.any(keep):
        raise EvaluationError("b_mag_cal", "no finite valid row", "at least one magnetometer sample")
    norm = np.linalg.norm(b_mag_cal[keep], axis=1)
    return float(np.sqrt(np.mean((norm - 1.0) ** 2)))
