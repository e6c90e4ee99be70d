"""BROAD benchmark trials (Laidig et al., Data 2021) as published: MATLAB `.mat` and `.hdf5`.

Fields: ``imu_gyr`` (N, 3) rad/s, ``imu_acc`` (N, 3) m/s², ``imu_mag`` (N, 3) µT, ``opt_quat`` (N, 4)
w,x,y,z sensor→ENU (magnetic north; NaN where tracking dropped), ``movement`` (N,) score mask,
``sampling_rate`` Hz. The units are already SI: nothing is converted.

Sampling rate in the HDF5 files: the published `.hdf5` has no ``sampling_rate`` dataset; it is a
root *attribute* (``f.attrs["sampling_rate"]`` = 285.714…, as the file's ``info`` attribute says).
The reader looks for a dataset, then a root attribute, and only when both are absent falls back to
BROAD's nominal 2000/7 Hz, recording ``meta["rate_source"] = "default"`` so the guess is visible.
MATLAB v7.3 `.mat` files are HDF5 too and take the same path; arrays stored transposed (3, N) are
turned to (N, 3).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from imugraph.errors import SessionError
from imugraph.io.session import Session

BROAD_RATE_HZ = 2000.0 / 7.0
FIELDS = ("imu_gyr", "imu_acc", "imu_mag")
MAT_ERRORS = (ValueError, TypeError, OSError, EOFError, IndexError, KeyError, AttributeError,
              NotImplementedError, zlib.error)


def _orient(src: str, field: str, arr, ncols: int) -> np.ndarray:
    """(N, ncols) float array; accepts MATLAB-transposed (ncols, N)."""
    a = np.asarray(arr)
    if a.dtype.kind not in "biuf":
        raise SessionError(src, field, f"dtype {a.dtype}", "a numeric array")
    a = a.astype(float)
    if a.ndim == 2 and a.shape[1] != ncols and a.shape[0] == ncols:
        a = a.T
    if a.ndim != 2 or a.shape[1] != ncols:
        raise SessionError(src, field, f"shape {a.shape}", f"shape (N, {ncols})")
    return a


def _rate(src: str, value) -> float:
    a = np.asarray(value, dtype=float).reshape(-1) if np.asarray(value).dtype.kind in "biuf" else np.array([])
    if a.size != 1 or not np.isfinite(a[0]) or a[0] <= 0:
        raise SessionError(src, "sampling_rate", f"{np.asarray(value)!r:.60}", "one positive number in Hz")
    return float(a[0])


def _session(src: str, fields: dict, rate: float, meta: dict) -> Session:
    for f in FIELDS:
        if f not in fields:
            raise SessionError(src, f, "missing", "BROAD fields imu_gyr, imu_acc, imu_mag (N, 3)")
    gyr = _orient(src, "imu_gyr", fields["imu_gyr"], 3)
    acc = _orient(src, "imu_acc", fields["imu_acc"], 3)
    mag = _orient(src, "imu_mag", fields["imu_mag"], 3)
    quat = _orient(src, "opt_quat", fields["opt_quat"], 4) if "opt_quat" in fields else None
    movement = None
    if "movement" in fields:
        movement = np.asarray(fields["movement"]).reshape(-1).astype(bool)
    n = gyr.shape[0]
    meta = {"format": meta.pop("format"), "rate_hz": rate, "mag_unit": "uT",
            "quat_frame": "ENU with magnetic north (OptiTrack)", "converted": [], **meta}
    return Session(t=np.arange(n) / rate, gyr=gyr, acc=acc, mag=mag, quat=quat, movement=movement,
                   source=src, name=Path(src).stem, meta=meta)


def read_broad_mat_fields(path: Path, fields: dict) -> Session:
    """Session from the variables of a BROAD v5 `.mat` already loaded by scipy.io.loadmat.

    Args:
        path: the file.
        fields: {name: array} as returned by loadmat.
    Returns:
        Session (rad/s, m/s², µT), t = k / sampling_rate.
    Raises:
        SessionError: a missing or malformed field.
    """
    src = str(path)
    if "sampling_rate" not in fields:
        raise SessionError(src, "sampling_rate", "missing", "the sampling rate in Hz")
    return _session(src, dict(fields), _rate(src, fields["sampling_rate"]), {"format": "broad-mat"})


def read_broad_hdf5(path: Path) -> Session:
    """Session from a BROAD `.hdf5` (or an HDF5-based MATLAB v7.3 `.mat` with the same fields).

    Args:
        path: the file.
    Returns:
        Session (rad/s, m/s², µT); ``meta["rate_source"]`` says where the rate came from.
    Raises:
        SessionError: unreadable HDF5, missing or malformed field.
    """
    import h5py

    src = str(path)
    try:
        with h5py.File(path, "r") as f:
            fields = {k: f[k][()] for k in (*FIELDS, "opt_quat", "movement", "sampling_rate")
                      if k in f and isinstance(f[k], h5py.Dataset)}
            attrs = {k: f.attrs[k] for k in f.attrs}
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise SessionError(src, "file", f"an unreadable HDF5 file ({exc})", "a BROAD .hdf5 file") from None
    if "sampling_rate" in fields:
        rate, how = _rate(src, fields.pop("sampling_rate")), "dataset"
    elif "sampling_rate" in attrs:
        rate, how = _rate(src, attrs["sampling_rate"]), "attribute"
    else:
        rate, how = BROAD_RATE_HZ, "default"
    return _session(src, fields, rate, {"format": "broad-hdf5", "rate_source": how})
