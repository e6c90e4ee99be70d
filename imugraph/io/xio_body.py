"""x-IMU3 body sessions: a folder of x-IMU3 export folders, one per sensor, read as one `BodySession`.

Layout (the x-IMU3 GUI's data logger, one network session)::

    <root>/<segment> <serial> (<interface>)/Inertial.csv, Magnetometer.csv[, Quaternion.csv, …]

e.g. ``pelvis 64F0EDBF (UDP)``, ``Left Upper Leg 64F61CC4 (UDP)``. Each sensor folder is read by
`imugraph.io.xio.read_ximu3_folder` (units to SI, held magnetometer rows dropped). The segment is the folder name
without the serial and the interface, matched without case, spaces, '_' or '-' to an MVN segment name
("pelvis" → Pelvis, "Left Upper Leg" → LeftUpperLeg, "Right Foot" → RightFoot; the 17 full-body names too).

Clock. The sensors of one x-IMU3 network session stamp their samples on one synchronised clock: on
../shared/data/xio_lower_body the seven first stamps lie within 17 ms of each other (917.41–917.43 s after the
clock's epoch) and the seven last stamps within 19 ms, while each sensor's own sample rate measured on that clock
differs (49.85–50.05 Hz, 0.4 %: 3.7 samples over the 18.6 s). Aligning by sample index would therefore drift by
≈ 74 ms; the stamps are used as they are (their spreads are in ``meta["clock"]``).

Common grid (X1). t_k = t_a + k·T, T = the median over the sensors of their median stamp step, t_a the latest
first stamp, up to the earliest last stamp (t in the session from 0 at t_a). Each sensor's gyr and acc are
linearly interpolated from its own stamps t_i ≤ t_k < t_{i+1}:

    x(t_k) = x_i + (t_k − t_i) / (t_{i+1} − t_i) · (x_{i+1} − x_i)                        (X1)

the onboard AHRS quaternion (an estimate, not ground truth) by slerp with the same fraction; the magnetometer
samples (Magnetometer.csv's own stamps) go to the nearest grid sample within T/2, NaN elsewhere (as
`read_ximu3_folder` places them on the inertial stamps).

Dropouts. The body graph takes no gap: `imugraph.graphs.body_model.check_session` wants finite gyr/acc on every
common sample and its preintegration has no missing-time model (the gaittoolbox reader refuses non-finite
samples). UDP dropouts (stamp steps > 1.5 T_i, the rule of `imugraph.factors.gaps`) of at most
`max_gap_samples` missing samples are bridged by (X1); a longer one inside the common span is a SessionError
naming the sensor, the time and the length. ``meta["dropouts"][segment]`` counts them (count, missing_samples,
bridged_grid_samples: grid samples that fell inside a dropout and are interpolated across it).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Union

import numpy as np

from imugraph.body.skeleton import FULL_BODY_SENSED, LOWER_BODY
from imugraph.errors import SessionError
from imugraph.factors.gaps import gap_steps
from imugraph.io.body_session import BodySession, default_skeleton
from imugraph.io.session import Session
from imugraph.io.xio import QUAT_SOURCE, _onboard_quat, _place_mag, read_ximu3_tables

PathLike = Union[str, Path]
SEGMENTS = tuple(dict.fromkeys(LOWER_BODY + FULL_BODY_SENSED))
MAX_GAP_SAMPLES = 3               # missing samples one dropout may hold and still be bridged by (X1)
_FOLDER = re.compile(r"^(?P<name>.*?)(?:\s+(?P<serial>[0-9A-Fa-f]{8}))?(?:\s*\((?P<iface>[^)]*)\))?\s*$")


def _key(name: str) -> str:
    return re.sub(r"[\s_\-]+", "", name).lower()


def segment_of(folder_name: str) -> tuple:
    """(MVN segment or None, serial or None) of an x-IMU3 folder name ('Left Upper Leg 64F61CC4 (UDP)')."""
    m = _FOLDER.match(folder_name)
    seg = {_key(s): s for s in SEGMENTS}.get(_key(m["name"]))
    return seg, m["serial"]


def sensor_folders(root: PathLike) -> list:
    """The subfolders of `root` that are x-IMU3 export folders (holding Inertial.csv), sorted by name."""
    root = Path(root)
    return sorted(c for c in root.iterdir() if c.is_dir() and (c / "Inertial.csv").is_file())


def is_ximu3_body_folder(path: PathLike) -> bool:
    """A folder (not itself an x-IMU3 folder) with at least one x-IMU3 export subfolder."""
    p = Path(path)
    return p.is_dir() and not (p / "Inertial.csv").is_file() and bool(sensor_folders(p))


def _gaps(src: str, seg: str, ts: np.ndarray, t_a: float, t_b: float, grid: np.ndarray,
          max_gap: int) -> dict:
    """Dropouts of one sensor inside [t_a, t_b] (`gap_steps` over the median step): counted, or refused when longer
    than max_gap missing samples; grid samples strictly inside a dropout are counted as bridged."""
    dt = np.diff(ts)
    med = float(np.median(dt))
    idx = np.flatnonzero(gap_steps(dt, med) & (ts[1:] > t_a) & (ts[:-1] < t_b))
    missing = np.round(dt[idx] / med).astype(int) - 1
    if idx.size and int(missing.max()) > max_gap:
        k = int(np.argmax(missing))
        i = int(idx[k])
        raise SessionError(src, f"sensors[{seg}].t", f"a dropout of {missing[k]} samples ({dt[i] * 1e3:.0f} ms) at "
                           f"t = {ts[i] - t_a:.3f} s of the common span", f"dropouts of ≤ {max_gap} samples (bridged "
                           "by interpolation; the body graph has no model for longer missing time)")
    bridged = sum(int(np.sum((grid > ts[i]) & (grid < ts[i + 1]))) for i in idx)
    return {"count": int(idx.size), "missing_samples": int(missing.sum()), "bridged_grid_samples": bridged,
            "at_s": [round(float(ts[i] - t_a), 4) for i in idx]}


INTERP = ("linear", "cubic", "akima")


def _resample(ts: np.ndarray, x: np.ndarray, grid: np.ndarray, how: str = "linear") -> np.ndarray:
    """x on the grid from the sensor's own stamps: 'linear' (X1) per column, or through the neighbours' curvature,
    'cubic' (a not-a-knot cubic spline, scipy CubicSpline) or 'akima' (modified Akima: no overshoot at steps)."""
    if how == "linear":
        return np.column_stack([np.interp(grid, ts, x[:, j]) for j in range(x.shape[1])])
    from scipy.interpolate import Akima1DInterpolator, CubicSpline

    f = CubicSpline(ts, x, axis=0) if how == "cubic" else Akima1DInterpolator(ts, x, axis=0, method="makima")
    return f(grid)


def _resample_quat(ts: np.ndarray, q: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Slerp between the bracketing samples with (X1)'s fraction."""
    from imugraph.geometry import quat_slerp

    j = np.clip(np.searchsorted(ts, grid, side="right") - 1, 0, ts.size - 2)
    u = np.clip((grid - ts[j]) / (ts[j + 1] - ts[j]), 0.0, 1.0)
    return quat_slerp(q[j], q[j + 1], u)


def read_ximu3_body(folder: PathLike, max_gap_samples: int = MAX_GAP_SAMPLES, interp: str = "linear") -> BodySession:
    """The x-IMU3 sensors of one recording as a BodySession on one common grid (module docstring).

    Args:
        folder: the folder holding one x-IMU3 export folder per sensor.
        max_gap_samples: longest UDP dropout (missing samples) bridged by interpolation; longer ones are refused.
        interp: how gyr and acc go onto the grid: 'linear' (X1, default), 'cubic' or 'akima' (`_resample`).
    Returns:
        BodySession (t from 0 s at the latest first stamp, sensors keyed by MVN segment, SI units, magnetometer in
        its own unit with NaN rows between its updates; each Session's quat is the onboard AHRS estimate, not ground
        truth; truth None; skeleton `default_skeleton` (the nominal 7-segment lower body or 17-sensor full body)).
    Raises:
        SessionError: no sensor folder, a folder name that is no segment, two folders on one segment, sensors
            that do not overlap in time, a dropout longer than max_gap_samples, or a sensor failing validation.
    """
    from imugraph.io.validate import validate_session

    root = Path(folder)
    src = str(root)
    if interp not in INTERP:
        raise SessionError(src, "interp", repr(interp), f"one of {', '.join(INTERP)}")
    subs = sensor_folders(root) if root.is_dir() else []
    if not subs:
        raise SessionError(src, "folders", "no x-IMU3 folder (a subfolder with Inertial.csv)",
                           "one x-IMU3 export folder per sensor, named '<segment> <serial> (<interface>)'")
    raw, serials = {}, {}
    for sub in subs:
        seg, serial = segment_of(sub.name)
        if seg is None:
            raise SessionError(str(sub), "folder name", repr(sub.name), "a segment name followed by the serial, one "
                               f"of {', '.join(SEGMENTS)} (case, spaces, '_' and '-' ignored: 'Left Upper Leg')")
        if seg in raw:
            raise SessionError(str(sub), "folder name", f"a second folder for {seg} (first: {raw[seg][0].name})",
                               "one x-IMU3 folder per segment")
        s = read_ximu3_tables(sub)                 # (ts, gyr, acc, tm, mag_raw, held, converted, mag_unit)
        ts = s[0]
        s += (_onboard_quat(sub, ts),)              # + the onboard AHRS quaternion or None
        if ts.size < 2 or not np.all(np.diff(ts) > 0):
            raise SessionError(str(sub / "Inertial.csv"), "Timestamp", "fewer than 2 or unsorted stamps",
                               "strictly increasing time stamps")
        raw[seg], serials[seg] = (sub, s, ts), serial
    first = np.array([v[2][0] for v in raw.values()])
    last = np.array([v[2][-1] for v in raw.values()])
    steps = {seg: float(np.median(np.diff(v[2]))) for seg, v in raw.items()}
    T = float(np.median(list(steps.values())))
    t_a, t_b = float(first.max()), float(last.min())
    if t_b - t_a < 2 * T:
        raise SessionError(src, "Timestamp", f"sensors spanning {first.min():.3f}–{last.max():.3f} s with a common "
                           f"span of {max(t_b - t_a, 0.0):.3f} s", "sensors of one recording on one clock")
    grid = t_a + T * np.arange(int(np.floor((t_b - t_a) / T + 1e-9)) + 1)
    t = grid - t_a
    sensors, dropouts, per_sensor = {}, {}, {}
    for seg, (sub, s, ts) in raw.items():
        dropouts[seg] = _gaps(str(sub / "Inertial.csv"), seg, ts, t_a, t_b, grid, max_gap_samples)
        _, s_gyr, s_acc, tm, mag_raw, held, converted, mag_unit, q_own = s
        gyr, acc = _resample(ts, s_gyr, grid, interp), _resample(ts, s_acc, grid, interp)
        quat = None if q_own is None else _resample_quat(ts, np.asarray(q_own, float), grid)
        keep = np.all(np.isfinite(mag_raw), axis=1)
        mag, unplaced = _place_mag(grid, tm[keep], mag_raw[keep])
        meta = {"converted": converted, "mag_unit": mag_unit, "mag_held": held}
        if q_own is not None:
            meta["quat_source"] = QUAT_SOURCE
        meta.update(format="x-imu3", folder=sub.name, serial=serials[seg], rate_hz=1.0 / steps[seg],
                    mag_outside_grid=unplaced, resampled=f"{interp} onto the common grid; quat slerp")
        sensors[seg] = validate_session(Session(t, gyr, acc, mag, quat, None, str(sub), seg, meta))
        per_sensor[seg] = {"folder": sub.name, "serial": serials[seg], "rate_hz": round(1.0 / steps[seg], 4),
                           "first_stamp_ms": round(float(raw[seg][2][0] - t_a) * 1e3, 3),
                           "magnetometer_samples": int(np.sum(np.all(np.isfinite(mag), axis=1)))}
    skel = default_skeleton(src, sensors)
    meta = {"format": "x-imu3-body", "rate_hz": 1.0 / T, "interpolation": f"{interp}, quat slerp",
            "clock": {"how": "the sensors' own synchronised x-IMU3 time stamps, one grid over their common span",
                      "start_stamp_s": t_a, "first_stamp_spread_ms": float((first.max() - first.min()) * 1e3),
                      "last_stamp_spread_ms": float((last.max() - last.min()) * 1e3),
                      "cut_start_s": float(t_a - first.min()), "cut_end_s": float(last.max() - t_b)},
            "max_gap_samples": int(max_gap_samples), "dropouts": dropouts, "sensors": per_sensor,
            "dropouts_total": {"count": sum(d["count"] for d in dropouts.values()),
                               "missing_samples": sum(d["missing_samples"] for d in dropouts.values()),
                               "bridged_grid_samples": sum(d["bridged_grid_samples"] for d in dropouts.values())},
            "skeleton": "nominal 1.75 m (imugraph.io.body_session.default_skeleton; subject's not known)"}
    return BodySession(t=t, sensors=sensors, skeleton=skel, truth=None, source=src, name=root.name, meta=meta)
