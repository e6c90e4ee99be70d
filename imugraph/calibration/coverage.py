"""What rotation a recording holds, and whether the magnetometer calibration is identifiable.

Kok et al. (FUSION 2012) need the sensor "rotated in all directions": the ellipsoid ([ellipsoid] in
`ellipsoid.py`) is determined only when the field direction spans three dimensions, and the axis
alignment ([inclination] in `alignment.py`) only when the sensor turns about at least two axes (see
`alignment.py` for the unobservable family). This module measures that in terms a user can act on:

- Every statistic is taken over samples picked at every `CELL_DEG` of rotation integrated from the
  gyro (bias removed, rates above the noise floor), so time spent at rest or turning back and forth
  over the same few degrees does not inflate the coverage, and sensor noise does not either.
- `acc_spread`: eigenvalues (ascending, summing to 1) of the scatter mean(u uᵀ) of the body "up"
  u_b (`alignment.gravity_up`, or bRn·e_z from a given orientation). A uniform
  sphere gives [⅓, ⅓, ⅓], a great circle [0, ½, ½], a sensor never tilted [0, 0, 1].
  `acc_octants`: fraction of the 8 octants of the sphere holding ≥ 1 % of those directions.
- `mag_spread`: eigenvalues of the covariance of the magnetometer POINTS, normalised to sum 1. It
  needs no centre or calibration (offset-free, scale-free): a sphere gives ≈ [⅓, ⅓, ⅓], a circle
  (one rotation axis) or a small cap of the sphere a first eigenvalue near 0.
- `rotation_deg`: rotation angle integrated per body axis ∫|ω_i|dt; `axis_share`: share of the rotation
  about the principal rotation axis (largest eigenvalue of Σ‖ω‖dt·ω̂ω̂ᵀ over its trace),
  `dominant_axis` that axis in body coordinates.

Thresholds (module constants) were set on BROAD and on simulated single-axis rotation. The 13 BROAD
trials that rotate give smallest mag spread 0.086–0.25, middle acc spread 0.15–0.40, axis share
0.41–0.80; the four "translation without rotation" trials (10, 12, 15, 16: tilts of 16–58°) give
smallest mag spread 0.022–0.033 (and 10, 12 middle acc spread 0.006). Those hold too little rotation
for the ellipsoid (its fit fails on them too) and are reported as not identifiable. A turntable
(one axis, gravity along it) gives axis share 1.0, mag spread 0 and acc spread 0.
"""

from __future__ import annotations

import numpy as np

from imugraph.calibration.alignment import gravity_up
from imugraph.errors import CalibrationError
from imugraph.geometry import quat_to_rotmat
from imugraph.io.session import Session

MAG_MIN_SPREAD = 0.05      # smallest eigenvalue of the magnetometer point covariance (sum 1)
ACC_MIN_SPREAD = 0.03      # middle eigenvalue of the "up" direction scatter (tilt about ≥ 2 axes)
MAX_AXIS_SHARE = 0.90      # share of the rotation about the principal axis
MIN_TOTAL_DEG = 180.0      # total rotation angle
GYR_NOISE_FLOOR = 0.05     # rad/s: slower samples are not counted as rotation
OCTANT_MIN_SHARE = 0.01    # of the picked directions
CELL_DEG = 5.0             # one sample per this much integrated rotation
_ADVICE = ("rotate the sensor about all three axes and record again, or pass --allow-weak (library: "
           "allow_weak=True) for a regularised estimate marked identifiable: false")


def _unit(v: np.ndarray) -> np.ndarray:
    """Finite, non-zero rows of (N, 3) v scaled to unit length, (M, 3)."""
    v = v[np.all(np.isfinite(v), axis=1)]
    n = np.linalg.norm(v, axis=1)
    return v[n > 0] / n[n > 0, None]


def pick_by_rotation(angle_deg: np.ndarray, mask: np.ndarray, step_deg: float = CELL_DEG) -> np.ndarray:
    """Indices of the first `mask` sample in every `step_deg` step of the cumulative rotation.

    Args:
        angle_deg: (N,) cumulative rotation angle, deg (from `integrated_rotation`).
        mask: (N,) bool candidate samples.
        step_deg: spacing, deg.

    Returns:
        (M,) int indices, increasing.
    """
    idx = np.flatnonzero(mask)
    _, first = np.unique(np.floor(angle_deg[idx] / step_deg), return_index=True)
    return idx[first]


def _direction_spread(u: np.ndarray) -> tuple[np.ndarray, float]:
    """(M, 3) unit vectors → (ascending eigenvalues of mean(u uᵀ) (3,), fraction of octants visited)."""
    if u.shape[0] == 0:
        return np.zeros(3), 0.0
    ev = np.clip(np.linalg.eigvalsh(u.T @ u / u.shape[0]), 0.0, None)
    octant = (u[:, 0] > 0) * 4 + (u[:, 1] > 0) * 2 + (u[:, 2] > 0)
    share = np.bincount(octant, minlength=8) / u.shape[0]
    return ev, float(np.mean(share >= OCTANT_MIN_SHARE))


def _point_spread(y: np.ndarray) -> np.ndarray:
    """(M, 3) points → ascending eigenvalues of their covariance, normalised to sum 1."""
    if y.shape[0] < 3:
        return np.zeros(3)
    ev = np.clip(np.linalg.eigvalsh(np.cov(y.T)), 0.0, None)
    return ev / ev.sum() if ev.sum() > 0 else ev


def _up_directions(session: Session, nRb: np.ndarray | None, gyro_bias: np.ndarray | None,
                   angle_deg: np.ndarray, b_up: np.ndarray | None = None) -> np.ndarray:
    """Body "up" u_b at the picked samples: bRn·e_z from nRb, else `gravity_up` (gyro + acc)."""
    if nRb is not None:
        nRb = np.asarray(nRb, float)
        if nRb.ndim == 2 and nRb.shape[1] == 4:         # quaternions w, x, y, z
            nRb = quat_to_rotmat(nRb)
        up = nRb[:, 2, :]                               # bRn e_z = row 2 of nRb
    else:
        up = gravity_up(session.gyr, session.acc, session.dt, gyro_bias) if b_up is None else b_up
    return _unit(up[pick_by_rotation(angle_deg, np.all(np.isfinite(up), axis=1))])


def integrated_rotation(session: Session,
                        gyro_bias: np.ndarray | None = None) -> tuple[dict, np.ndarray]:
    """Rotation the gyro saw (rates below GYR_NOISE_FLOOR count as zero).

    Args:
        session: the recording (gyr rad/s).
        gyro_bias: optional (3,) rad/s removed first.

    Returns:
        (summary, angle_deg): summary dict with rotation_deg (3, per body axis ∫|ω_i|dt, deg),
        total_rotation_deg, axis_share, dominant_axis (3,); angle_deg (N,) cumulative angle, deg.
    """
    w = np.asarray(session.gyr, float) - (0.0 if gyro_bias is None else np.asarray(gyro_bias))
    speed = np.linalg.norm(w, axis=1)
    keep = np.isfinite(speed) & (speed > GYR_NOISE_FLOOR)
    w_dt = np.where(keep[:, None], w, 0.0) * session.dt[:, None]          # (N, 3) rad
    step = np.where(keep, speed, 0.0) * session.dt                        # (N,) rad
    W = (w_dt / np.where(step > 0, step, 1.0)[:, None]).T @ w_dt           # Σ ‖ω‖dt ω̂ω̂ᵀ
    lam, V = np.linalg.eigh(W)
    share = float(lam[-1] / lam.sum()) if lam.sum() > 0 else 1.0
    axis = V[:, -1] * np.sign(V[np.argmax(np.abs(V[:, -1])), -1])
    angle_deg = np.degrees(np.cumsum(step))
    return {"rotation_deg": np.degrees(np.abs(w_dt).sum(axis=0)).tolist(),
            "total_rotation_deg": float(angle_deg[-1]) if angle_deg.size else 0.0,
            "axis_share": share, "dominant_axis": axis.tolist()}, angle_deg


def _axis_name(axis: np.ndarray) -> str:
    """"body z" for a (3,) unit axis within 18° of a body axis, else its coordinates."""
    i = int(np.argmax(np.abs(axis)))
    if abs(axis[i]) > 0.95:
        return f"body {'xyz'[i]}"
    return "body axis [" + ", ".join(f"{a:.2f}" for a in axis) + "]"


def _problems(cov: dict) -> list[str]:
    """Sentences naming each threshold the coverage dict fails (empty: identifiable)."""
    out = []
    if cov["total_rotation_deg"] < MIN_TOTAL_DEG:
        out.append(f"the sensor hardly rotated (total {cov['total_rotation_deg']:.0f}°, need ≥ "
                   f"{MIN_TOTAL_DEG:.0f}°)")
    if cov["axis_share"] > MAX_AXIS_SHARE:
        out.append(f"rotation about one axis only ({_axis_name(np.array(cov['dominant_axis']))} holds "
                   f"{100 * cov['axis_share']:.0f} % of the rotation)")
    if cov["mag_samples"] == 0:
        out.append("no magnetometer samples: the magnetometer cannot be calibrated")
    elif cov["mag_spread"][0] < MAG_MIN_SPREAD:
        out.append(f"the magnetometer readings cover only a circle or a small cap of the sphere "
                   f"(smallest spread {cov['mag_spread'][0]:.3f}, need ≥ {MAG_MIN_SPREAD})")
    if cov["acc_spread"][1] < ACC_MIN_SPREAD:
        out.append(f"gravity stays near one body direction (the sensor was hardly tilted; spread "
                   f"{cov['acc_spread'][1]:.3f}, need ≥ {ACC_MIN_SPREAD})")
    return out


def rotation_coverage(session: Session, nRb: np.ndarray | None = None,
                      gyro_bias: np.ndarray | None = None, b_up: np.ndarray | None = None) -> dict:
    """Describe the rotation a recording holds and decide whether the calibration is identifiable.

    Args:
        session: the recording (gyr rad/s, acc m/s², mag any unit with NaN rows).
        nRb: optional orientation body→nav, (N, 3, 3) or quaternions (N, 4) w,x,y,z (truth or
            estimate; NaN rows ignored); replaces the accelerometer for "up".
        gyro_bias: optional (3,) rad/s removed before integrating the gyro.

    Returns:
        JSON-ready dict: acc_spread, mag_spread (3 ascending eigenvalues each), acc_octants
        (fraction), mag_samples (valid rows), rotation_deg (3, per body axis), total_rotation_deg,
        axis_share, dominant_axis (3,), identifiable (bool), problems (list of sentences).
    """
    cov, angle_deg = integrated_rotation(session, gyro_bias)
    acc_ev, acc_oct = _direction_spread(_up_directions(session, nRb, gyro_bias, angle_deg, b_up))
    mag = np.asarray(session.mag, float)
    valid = np.all(np.isfinite(mag), axis=1)
    mag_ev = _point_spread(mag[pick_by_rotation(angle_deg, valid)]) if valid.any() else np.zeros(3)
    cov.update({"acc_spread": acc_ev.tolist(), "acc_octants": acc_oct, "mag_spread": mag_ev.tolist(),
                "mag_samples": int(valid.sum())})
    cov["problems"] = _problems(cov)
    cov["identifiable"] = not cov["problems"]
    return cov


def check_coverage(session: Session, nRb: np.ndarray | None = None,
                   gyro_bias: np.ndarray | None = None, b_up: np.ndarray | None = None) -> dict:
    """`rotation_coverage`, raising when the calibration is not identifiable.

    Returns:
        the coverage dict (identifiable is True).

    Raises:
        CalibrationError: naming the file, the field 'mag' and every problem found.
    """
    cov = rotation_coverage(session, nRb, gyro_bias, b_up)
    if not cov["identifiable"]:
        raise CalibrationError(f"{session.source}: field 'mag': found too little rotation to calibrate: "
                               + "; ".join(cov["problems"])
                               + f"; expected data that identify D and o: {_ADVICE}")
    return cov


def mag_spread_of_rows(session: Session, used: np.ndarray, gyro_bias: np.ndarray | None = None) -> float:
    """Smallest `mag_spread` eigenvalue of the magnetometer rows `used` (N,) bool (e.g. outside the disturbance
    windows a solve leaves out), picked at every CELL_DEG of rotation as `rotation_coverage` picks them; 0 when
    fewer than 3 rows. `rotation_coverage` judges the whole recording; this judges the rows a solve keeps
    (BROAD 34's first 67 s: 0.155 whole, 0.011 without its magnet windows, < MAG_MIN_SPREAD = 0.05)."""
    _, angle_deg = integrated_rotation(session, gyro_bias)
    mag = np.asarray(session.mag, float)
    rows = np.asarray(used, bool) & np.all(np.isfinite(mag), axis=1)
    return float(_point_spread(mag[pick_by_rotation(angle_deg, rows)])[0]) if rows.any() else 0.0
