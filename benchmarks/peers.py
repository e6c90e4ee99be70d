"""Peer estimators imugraph is compared against: VQF (online and offline) and "ellipsoid fit + VQF".

VQF (Laidig & Seel, Information Fusion 91:187–204, 2023; `pip install vqf`) returns quaternions w,x,y,z
that rotate sensor-frame vectors into its earth frame (sensor → earth, the same sense as our nRb). Its
earth frame is ENU: z up, and in 9D the horizontal magnetic field along +y (it drives
atan2(m_x, m_y) → 0). imugraph's nav frame has z up and the horizontal field along +x, so

    n_v = Rz(−90°) · e_v   ⇒   q_nb = q_z(−90°) ⊗ q_eb,

which these wrappers apply unless `enu=True`. (In 6D the heading is arbitrary in either frame; the
metric in imugraph.evaluate removes a constant heading offset anyway.)

VQF needs float64, C-contiguous arrays and a magnetometer sample on every row. Multi-rate logs store NaN
rows between magnetometer samples (Session convention): these wrappers hold the last sample (zero-order
hold, as most logging firmware does), and fill leading NaN rows with the first sample.

The ellipsoid peer is "what users do today": an algebraic least-squares ellipsoid fit of the
magnetometer alone (no inertial information, so the misalignment between magnetometer and inertial
axes stays uncorrected), written here independently of imugraph's own calibration.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Optional

import numpy as np

from imugraph.errors import CalibrationError, SessionError
from imugraph.io.session import Session

# q_z(−90°): rotates VQF's ENU (field along +y) into imugraph's nav frame (field along +x).
_Q_NAV_FROM_ENU = np.array([np.cos(-np.pi / 4), 0.0, 0.0, np.sin(-np.pi / 4)])


def timed(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, float]:
    """Run fn(*args, **kwargs) and return (result, wall-clock seconds)."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def hold_mag(mag: np.ndarray, source: str = "<memory>") -> np.ndarray:
    """Zero-order hold of a magnetometer with NaN rows (no sample) onto every row.

    Args:
        mag: (N, 3) field, any unit, NaN rows where no sample arrived.
        source: file name for the error message.

    Returns:
        (N, 3) float64 C-contiguous: each NaN row repeats the last sample before it (leading NaN rows
        take the first sample).

    Raises:
        SessionError: no finite magnetometer row at all.
    """
    mag = np.asarray(mag, float)
    valid = np.all(np.isfinite(mag), axis=1)
    if not np.any(valid):
        raise SessionError(source, "mag", "no finite magnetometer row", "at least one sample for 9D VQF")
    last = np.where(valid, np.arange(mag.shape[0]), 0)
    np.maximum.accumulate(last, out=last)
    last[: np.argmax(valid)] = np.argmax(valid)
    return np.ascontiguousarray(mag[last])


def _to_nav(quat_enu: np.ndarray, enu: bool) -> np.ndarray:
    """VQF's q_eb (N, 4) → imugraph's q_nb = q_z(−90°) ⊗ q_eb (or unchanged when enu)."""
    q = np.asarray(quat_enu, float)
    if enu:
        return q.copy()
    a0, a3 = _Q_NAV_FROM_ENU[0], _Q_NAV_FROM_ENU[3]
    w, x, y, z = q.T
    out = np.stack([a0 * w - a3 * z, a0 * x - a3 * y, a0 * y + a3 * x, a0 * z + a3 * w], axis=1)
    return out * np.where(out[:, :1] < 0, -1.0, 1.0)


def _vqf_inputs(session: Session, mag: Optional[np.ndarray], use_mag: bool):
    gyr = np.ascontiguousarray(session.gyr, dtype=np.float64)
    acc = np.ascontiguousarray(session.acc, dtype=np.float64)
    if not use_mag:
        return gyr, acc, None
    return gyr, acc, hold_mag(session.mag if mag is None else mag, session.source)


def vqf_offline(session: Session, mag: Optional[np.ndarray] = None, *, use_mag: bool = True,
                enu: bool = False) -> np.ndarray:
    """Offline (acausal) VQF, `vqf.offlineVQF(gyr, acc, mag, Ts)`.

    Args:
        session: the recording (gyr rad/s, acc m/s², constant rate).
        mag: (N, 3) magnetometer to use instead of session.mag (e.g. a distorted or calibrated field),
            any unit; None → session.mag. NaN rows are held (see module docstring).
        use_mag: False runs 6D VQF (no magnetometer, heading drifts).
        enu: return VQF's own ENU frame instead of imugraph's nav frame.

    Returns:
        (N, 4) quaternions w,x,y,z, sensor → nav (quat9D, or quat6D when use_mag is False).

    Raises:
        SessionError: no finite magnetometer row.
    """
    import vqf

    gyr, acc, b_mag = _vqf_inputs(session, mag, use_mag)
    out = vqf.offlineVQF(gyr, acc, b_mag, 1.0 / session.rate)
    return _to_nav(out["quat9D"] if use_mag else out["quat6D"], enu)


def vqf_online(session: Session, mag: Optional[np.ndarray] = None, *, use_mag: bool = True,
               enu: bool = False) -> np.ndarray:
    """Causal VQF, `vqf.VQF(Ts).updateBatch(gyr, acc, mag)`: the estimate available at each sample.

    Args:
        session, mag, use_mag, enu: as `vqf_offline`.

    Returns:
        (N, 4) quaternions w,x,y,z, sensor → nav.

    Raises:
        SessionError: no finite magnetometer row.
    """
    import vqf

    gyr, acc, b_mag = _vqf_inputs(session, mag, use_mag)
    out = vqf.VQF(1.0 / session.rate).updateBatch(gyr, acc, b_mag)
    return _to_nav(out["quat9D"] if use_mag else out["quat6D"], enu)


def fit_ellipsoid(b_mag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic least-squares ellipsoid fit: (b − o)ᵀ M (b − o) = 1 with M symmetric positive definite.

    Solves [x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z] · v = 1 for the quadric bᵀAb + 2gᵀb = 1 on centred and
    scaled samples; then o = −A⁻¹g and M = A / (1 + oᵀAo).

    Args:
        b_mag: (K, 3) finite magnetometer samples, any unit, K ≥ 9 and spread over many directions.

    Returns:
        (C, o): C = M^{1/2} (3×3, symmetric, 1/unit) and o (3,) in the input unit, so that C (b − o)
        has unit norm.

    Raises:
        CalibrationError: too few samples or the quadric is not an ellipsoid.
    """
    b_mag = np.asarray(b_mag, float)
    if b_mag.ndim != 2 or b_mag.shape[1] != 3 or b_mag.shape[0] < 9:
        raise CalibrationError(f"fit_ellipsoid: field 'b_mag': found shape {b_mag.shape}; expected (K ≥ 9, 3)")
    mu, sigma = b_mag.mean(axis=0), b_mag.std() + 1e-300
    x, y, z = ((b_mag - mu) / sigma).T
    design = np.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z], axis=1)
    v, *_ = np.linalg.lstsq(design, np.ones(x.size), rcond=None)
    A = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    g = v[6:]
    try:
        o_scaled = -np.linalg.solve(A, g)
    except np.linalg.LinAlgError as exc:
        raise CalibrationError("fit_ellipsoid: field 'b_mag': found a singular quadric; expected an "
                               "ellipsoid (rotate the sensor through more directions)") from exc
    M = A / (1.0 + o_scaled @ A @ o_scaled)
    evals, evecs = np.linalg.eigh(M)
    if np.any(evals <= 0):
        raise CalibrationError(f"fit_ellipsoid: field 'b_mag': found quadric eigenvalues {evals}; "
                               "expected all positive (an ellipsoid)")
    C = (evecs * np.sqrt(evals)) @ evecs.T / sigma
    return C, mu + sigma * o_scaled


def ellipsoid_calibrated_mag(session: Session, mag: Optional[np.ndarray] = None) -> np.ndarray:
    """Calibrate the magnetometer by a plain ellipsoid fit: C (b_mag − o), unit norm.

    Args:
        session: the recording; its magnetometer is used unless `mag` is given.
        mag: (N, 3) magnetometer to calibrate instead (any unit, NaN rows kept as NaN).

    Returns:
        (N, 3) calibrated field (unit norm where fitted well), NaN rows where the input has none.

    Raises:
        CalibrationError: the fit is not an ellipsoid.
    """
    b_mag = np.asarray(session.mag if mag is None else mag, float)
    valid = np.all(np.isfinite(b_mag), axis=1)
    C, o = fit_ellipsoid(b_mag[valid])
    out = np.full_like(b_mag, np.nan)
    out[valid] = (b_mag[valid] - o) @ C.T
    return out


def vqf_offline_ellipsoid(session: Session, mag: Optional[np.ndarray] = None) -> np.ndarray:
    """Offline VQF fed the ellipsoid-calibrated field (session.mag, or `mag` e.g. a distorted field).

    Args:
        session: the recording.
        mag: (N, 3) magnetometer to calibrate and use instead of session.mag.

    Returns:
        (N, 4) quaternions w,x,y,z, sensor → nav.

    Raises:
        CalibrationError: the ellipsoid fit failed.
    """
    return vqf_offline(session, mag=ellipsoid_calibrated_mag(session, mag))
