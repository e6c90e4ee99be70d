"""Rasteiro IMU dataset (IPLeiria): ``DataSets/<speed>/<seq>/<SENSOR>.mat`` with an ABB robot as truth.

Raw 9-axis sensors read here: LSM9DS0, MPU9150, MPU6050RM3100, MPU6500RM3100 (the files XSENS,
SENTRAL, *DMP hold commercial AHRS outputs and are refused). Variables are stored (3, N):

- ``SENSacc`` in g → × 9.80665 m/s² (median |acc| ≈ 1.00 in every file).
- ``SENSgyro``: units differ per sensor, found by integrating the gyroscope over 0.25 s windows and
  comparing the rotation angle with the robot's (best time shift, frame alignment fitted):
  MPU* are °/s (after × π/180 the gain against the robot is 0.97–1.00 on V_300 and eV50p);
  LSM9DS0 is rad/s-like but reads 0.86–0.875 of the robot's rate (0.8588/0.8751 on
  V_300/eV50p, same procedure), so it is divided by `LSM9DS0_GAIN` = 0.87.
- ``SENSmag`` raw uncalibrated counts, kept as they are (meta["mag_unit"] = "counts").
- ``MATLABtime`` s from the start of the log; the sensor clock has jitter (steps 2–40 ms).
  One bogus row (time 0, NaN data) sits near index 367 in the V_300/V1000 files: rows with
  non-finite time or inertial data are dropped (``meta["dropped_rows"]``). Wireless-link gaps
  longer than 5 median steps are declared in ``meta["gaps"]``.
- ``ABBquaternion`` (4, N), robot flange orientation interpolated to the sensor samples.
  Convention, checked on the data: **w first**, and it maps the robot base (z up) *to* the tool,
  i.e. it is bRn, so nRb = conj(q). Evidence: (i) fitting the gyroscope's integrated rotations
  to the robot's relative rotations gives a proper frame alignment (det > 0) only with the
  conjugate (det −0.66…−0.94 for q as nRb in the slow files); (ii) on the V1000 files, where
  orientations span ~140°, gravity seen by the accelerometer at quiet samples matches the base z
  axis mapped through q within 0.6–2.0° versus 2.9–3.6° with q read as nRb. (The equivalent
  reading "w last, nRb" would need the base's *x* axis to be vertical; q starts at ≈ [1, 0, 0, 0].)
- The sensor is mounted on the tool with an unknown rotation; the reader estimates it from the
  accelerometer at quiet samples (Kabsch fit of gravity directions) and returns
  ``quat`` = nRb of the *sensor* (nav = robot base, z up; heading arbitrary, not magnetic),
  with the fit's median residual in ``meta["truth_alignment_deg"]``.
- The robot truth lags the sensor data by 0–0.25 s depending on the file: score at the best shift.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import quat_conj, quat_mul, quat_to_rotmat, rotmat_to_quat
from imugraph.io.session import Session

G_STD = 9.80665
LSM9DS0_GAIN = 0.87
SENSORS = {"LSM9DS0": (1.0 / LSM9DS0_GAIN, "gyr: LSM9DS0 units (0.87 rad/s per unit, measured)->rad/s"),
           "MPU9150": (np.pi / 180.0, "gyr: deg/s->rad/s"),
           "MPU6050RM3100": (np.pi / 180.0, "gyr: deg/s->rad/s"),
           "MPU6500RM3100": (np.pi / 180.0, "gyr: deg/s->rad/s")}
VARIABLES = ("SENSgyro", "SENSacc", "SENSmag", "MATLABtime", "ABBquaternion")


def _rows(src: str, fields: dict, name: str, ncols: int) -> np.ndarray:
    if name not in fields:
        raise SessionError(src, name, "missing", f"Rasteiro variable {name} ({ncols}, N)")
    a = np.asarray(fields[name])
    if a.dtype.kind not in "biuf" or a.ndim != 2 or ncols not in a.shape:
        raise SessionError(src, name, f"shape {a.shape} dtype {a.dtype}", f"a numeric ({ncols}, N) array")
    a = a.astype(float)
    return a.T if a.shape[0] == ncols and a.shape[1] != ncols else a


def _kabsch(b_from: np.ndarray, b_to: np.ndarray) -> np.ndarray:
    """Rotation R minimising Σ|R·from − to|² for (M, 3) unit vectors (proper, det +1)."""
    U, _, Vt = np.linalg.svd(b_from.T @ b_to)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def sensor_alignment(acc: np.ndarray, gyr: np.ndarray, nRt: np.ndarray) -> Optional[tuple[np.ndarray, float]]:
    """Estimate sRt (tool → sensor) from gravity at quiet samples.

    At rest b_acc ∝ bRn·e_z (the accelerometer reads +g up), and the robot gives t_up = tRn·e_z,
    so b_acc/|b_acc| ≈ sRt·t_up: a Kabsch fit over the quiet samples.

    Args:
        acc: (N, 3) m/s².  gyr: (N, 3) rad/s.  nRt: (N, 4) w,x,y,z tool → base.
    Returns:
        (sRt (3, 3), median residual angle in degrees), or None when too few quiet samples span
        too little orientation to fix the rotation.
    """
    a_norm = np.linalg.norm(acc, axis=1)
    w_norm = np.linalg.norm(gyr, axis=1)
    quiet = (np.abs(a_norm - G_STD) < 0.05 * G_STD) & (w_norm < np.median(w_norm))
    if quiet.sum() < 20:
        return None
    s_up = acc[quiet] / a_norm[quiet, None]
    t_up = quat_to_rotmat(nRt[quiet])[:, 2, :]           # tRn·e_z = row 2 of nRt
    sv = np.linalg.svd(t_up, compute_uv=False)
    if sv[1] < 0.05 * sv[0]:                            # one direction only: rotation about it free
        return None
    sRt = _kabsch(t_up, s_up)
    cos = np.clip(np.sum((t_up @ sRt.T) * s_up, axis=1), -1.0, 1.0)
    return sRt, float(np.degrees(np.median(np.arccos(cos))))


def read_rasteiro_fields(path: Path, fields: dict) -> Session:
    """Session from the variables of a Rasteiro sensor .mat already loaded by scipy.io.loadmat.

    Args:
        path: the file (its stem names the sensor).
        fields: {name: array} from loadmat.
    Returns:
        Session (rad/s, m/s², magnetometer counts), truth nRb of the sensor in `quat`.
    Raises:
        SessionError: a reference-AHRS file, missing or malformed variables.
    """
    src = str(path)
    sensor = path.stem.upper()
    if sensor not in SENSORS:
        raise SessionError(src, "SENSgyro", f"a file of sensor '{path.stem}': a commercial AHRS's own orientation "
                           "output, refused (imugraph needs raw gyroscope, accelerometer and magnetometer samples)",
                           f"one of the raw sensors {', '.join(SENSORS)}")
    gyr, acc, mag = (_rows(src, fields, k, 3) for k in ("SENSgyro", "SENSacc", "SENSmag"))
    t = _rows(src, fields, "MATLABtime", 1).reshape(-1)
    q_abb = _rows(src, fields, "ABBquaternion", 4)
    n = t.size
    for name, arr in (("SENSgyro", gyr), ("SENSacc", acc), ("SENSmag", mag), ("ABBquaternion", q_abb)):
        if arr.shape[0] != n:
            raise SessionError(src, name, f"{arr.shape[0]} samples", f"{n} samples, as MATLABtime")
    ok = np.isfinite(t) & np.all(np.isfinite(gyr), 1) & np.all(np.isfinite(acc), 1)
    dropped = np.flatnonzero(~ok).tolist()
    # every raw file starts with an all-zero row (a placeholder, not a measurement: zero specific force); in
    # eV50p MPU6050/MPU6500 it is followed by a 0.1–0.3 s gap, so it became a keyframe of its own with no "up"
    blank = ok & np.all(gyr == 0, 1) & np.all(acc == 0, 1) & np.all(np.nan_to_num(mag) == 0, 1)
    ok &= ~blank
    t, gyr, acc, mag, q_abb = t[ok], gyr[ok], acc[ok], mag[ok], q_abb[ok]
    scale, note = SENSORS[sensor]
    gyr, acc = gyr * scale, acc * G_STD
    meta = {"format": "rasteiro", "sensor": sensor, "converted": [note, "acc: g->m/s^2"],
            "mag_unit": "counts", "dropped_rows": dropped, "blank_rows": np.flatnonzero(blank).tolist(),
            "quat_frame": "robot base (z up), heading arbitrary"}
    t0 = t[0] if t.size else 0.0
    if t.size > 1:                       # on the session's time base (t − t0: t0 is no longer 0 once row 0 is blank)
        dt = np.diff(t)
        gap = np.flatnonzero(dt > 5.0 * np.median(dt))
        meta["gaps"] = [[float(t[i] - t0), float(t[i + 1] - t0)] for i in gap]
    quat = _truth(q_abb, acc, gyr, meta)
    return Session(t=t - t0, gyr=gyr, acc=acc, mag=mag, quat=quat, source=src,
                   name=f"{path.parent.parent.name}_{path.parent.name}_{path.stem}", meta=meta)


def _truth(q_abb: np.ndarray, acc: np.ndarray, gyr: np.ndarray, meta: dict) -> np.ndarray:
    """nRb of the sensor from the ABB quaternion (w first, bRn of the tool) and the fitted mount."""
    norm = np.linalg.norm(q_abb, axis=1, keepdims=True)
    nRt = quat_conj(q_abb / np.where(norm > 0, norm, np.nan))
    fit = sensor_alignment(acc, gyr, nRt) if nRt.shape[0] else None
    if fit is None:
        meta["truth_alignment_deg"] = None
        meta["quat_frame"] += "; tool frame (sensor mount not identifiable)"
        return nRt
    sRt, resid = fit
    meta["truth_alignment_deg"] = resid
    meta["sensor_R_tool"] = sRt.tolist()
    tRs = rotmat_to_quat(sRt.T)
    return quat_mul(nRt, np.broadcast_to(tRs, nRt.shape))   # nRs = nRt · tRs
