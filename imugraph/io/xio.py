"""x-io Technologies CSV exports: the Fusion `sensor_data.csv` style and the x-IMU3 folder.

Headers name the quantity, axis and unit: ``Time (s)``, ``Timestamp (us)``,
``Gyroscope X (deg/s)``, ``Accelerometer X (g)``, ``Magnetometer X (uT)``, or in an x-IMU3
``Magnetometer.csv`` just ``X (a.u.)``. Readers convert to SI (rad/s, m/s², s) and record each
conversion in ``meta["converted"]``; the magnetometer keeps its unit.

Magnetometer samples *held* between updates (identical consecutive rows, as in Fusion's file where
a ~20 Hz magnetometer is repeated in a ~99 Hz stream) are used once: the first row of each run is
kept and the held copies become NaN (``meta["mag_held"]`` counts them).

The x-IMU3 folder holds ``Inertial.csv`` (µs time stamps, °/s, g) and ``Magnetometer.csv`` on its own
time stamps at a lower rate. Each magnetometer sample goes to the nearest inertial sample (if within
half an inertial step), NaN elsewhere. UDP dropouts (steps > 1.5 median steps) are reported in
``meta["dropouts"]`` and declared in ``meta["gaps"]`` instead of failing.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.io.session import Session
from imugraph.io.validate import NO_MAG

G_STD = 9.80665
_QUANTITY = {"gyroscope": "gyr", "accelerometer": "acc", "magnetometer": "mag"}
_COL = re.compile(r"^\s*(?:(gyroscope|accelerometer|magnetometer)\s+)?([xyz])\s*\(([^)]*)\)\s*$", re.I)
_TIME = re.compile(r"^\s*(time|timestamp)\s*\(\s*(s|ms|us|µs)\s*\)\s*$", re.I)
_TIME_SCALE = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
_TO_SI = {("gyr", "deg/s"): (np.pi / 180.0, "gyr: deg/s->rad/s"), ("gyr", "rad/s"): (1.0, None),
          ("acc", "g"): (G_STD, "acc: g->m/s^2"), ("acc", "m/s^2"): (1.0, None), ("acc", "m/s²"): (1.0, None)}


def read_csv_table(path: Path) -> tuple[list, np.ndarray]:
    """Read a comma-separated table with one header line; empty fields become NaN.

    A header line without a comma but with tabs or semicolons (a spreadsheet's export) names the separator, as in
    the Xsens reader (`imugraph.io.xsens.column_delimiter` and `to_commas`: a decimal comma is then read as a
    decimal point); a header holding a comma keeps the comma, so comma files read exactly as before.

    Args:
        path: file to read.
    Returns:
        (column names stripped, (N, C) float array).
    Raises:
        SessionError: empty file, non-text bytes, or malformed rows (see `parse_csv_lines`).
    """
    src = str(path)
    try:
        with open(path, "r", encoding="utf-8-sig") as fh:
            text = fh.read()
    except UnicodeDecodeError as exc:
        raise SessionError(src, "file", f"bytes that are not UTF-8 text ({exc.reason})", "a CSV text file") from None
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise SessionError(src, "file", "an empty file", "a CSV header line and data rows")
    from imugraph.io.xsens import column_delimiter, to_commas      # (xsens imports this module: not at the top)

    delim = "," if "," in lines[0] else column_delimiter(lines[0])
    cols = [c.strip() for c in lines[0].split(delim)]
    return cols, parse_csv_lines(src, cols, to_commas(lines[1:], delim), first_line=2)


def parse_csv_lines(src: str, cols: list, lines: list, first_line: int = 2) -> np.ndarray:
    """Parse comma-separated data lines into a float array (empty cells → NaN).

    Args:
        src: file name for messages.
        cols: column names (C of them).
        lines: data lines (blank lines are skipped).
        first_line: 1-based line number of lines[0] in the file, for messages.
    Returns:
        (N, C) float array.
    Raises:
        SessionError: a row with the wrong number of values (naming the line and the first missing
            column: usually a truncated file) or text where a number belongs.
    """
    counts = np.fromiter((ln.count(",") + 1 if ln.strip() else len(cols) for ln in lines), int, len(lines))
    wrong = np.flatnonzero(counts != len(cols))
    if wrong.size:
        i = int(wrong[0])
        missing = cols[min(int(counts[i]), len(cols) - 1)]
        raise SessionError(src, missing, f"line {i + first_line} has {counts[i]} of {len(cols)} values "
                           f"({wrong.size} such lines; truncated file?)", f"{len(cols)} comma-separated values")
    keep = [i for i, ln in enumerate(lines) if ln.strip()]
    rows = [lines[i] for i in keep]
    if not rows:
        return np.empty((0, len(cols)))
    try:
        return np.loadtxt(rows, delimiter=",", dtype=float, ndmin=2)
    except ValueError:
        pass                                   # empty cells (multi-rate logs) or text: slow path
    data = np.genfromtxt(rows, delimiter=",", dtype=float).reshape(len(rows), len(cols))
    for r in np.flatnonzero(np.isnan(data).any(axis=1)):
        cells = rows[r].split(",")
        for c in np.flatnonzero(np.isnan(data[r])):
            if cells[c].strip().lower() not in ("", "nan"):
                raise SessionError(src, cols[c], f"text {cells[c].strip()!r} on line {keep[r] + first_line}",
                                   "a number")
    return data


def parse_xio_header(cols: list, quantity: Optional[str] = None) -> dict:
    """Map x-io column names to (quantity, axis) → (column index, unit).

    Args:
        cols: header names.
        quantity: quantity for bare ``X (a.u.)`` columns (x-IMU3 per-sensor files).
    Returns:
        {"t": (index, unit)} plus {("gyr", "x"): (index, unit), ...}.
    """
    out: dict = {}
    for i, name in enumerate(cols):
        m = _TIME.match(name)
        if m:
            out["t"] = (i, m.group(2).lower())
            continue
        m = _COL.match(name)
        if m:
            q = _QUANTITY.get((m.group(1) or "").lower(), quantity)
            if q is not None:
                out[(q, m.group(2).lower())] = (i, m.group(3).strip())
    return out


def is_xio_header(cols: list) -> bool:
    """True when the header looks like an x-io export (time plus gyroscope columns with units)."""
    spec = parse_xio_header(cols)
    return "t" in spec and ("gyr", "x") in spec


def _block(src: str, spec: dict, data: np.ndarray, q: str, converted: list) -> np.ndarray:
    """(N, 3) block of quantity q converted to SI (gyr, acc) or kept (mag)."""
    label = {v: k.capitalize() for k, v in _QUANTITY.items()}[q]
    for ax in "xyz":
        if (q, ax) not in spec:
            name = f"{label} {ax.upper()}"
            if q == "mag" and not any(k[0] == "mag" for k in spec if isinstance(k, tuple)):   # a 6-axis export
                raise SessionError(src, name, "no magnetometer columns (a 6-axis recording)", NO_MAG)
            raise SessionError(src, name, "column missing", f"an x-io column '{name} (unit)'")
    units = sorted({spec[(q, ax)][1] for ax in "xyz"})
    if len(units) != 1:
        raise SessionError(src, label, f"mixed units {units}", "one unit for the three axes")
    unit = units[0]
    block = data[:, [spec[(q, ax)][0] for ax in "xyz"]]
    if q == "mag":
        return block
    if (q, unit) not in _TO_SI:
        raise SessionError(src, label, f"unit '{unit}'", "deg/s or rad/s (gyroscope), g or m/s^2 (accelerometer)")
    scale, note = _TO_SI[(q, unit)]
    if note:
        converted.append(note)
    return block * scale


def drop_held_rows(mag: np.ndarray) -> tuple[np.ndarray, int]:
    """NaN the held copies of a magnetometer (rows identical to the previous valid row).

    Args:
        mag: (N, 3) magnetometer, NaN rows for no sample.
    Returns:
        (a new (N, 3) array keeping the first row of each run of identical rows, number of held rows).
    """
    out = np.array(mag, float, copy=True)
    valid = np.flatnonzero(np.all(np.isfinite(out), axis=1))
    same = np.all(out[valid[1:]] == out[valid[:-1]], axis=1)
    held = valid[1:][same]
    out[held] = np.nan
    return out, int(held.size)


def _dropouts(t: np.ndarray) -> tuple[dict, list]:
    """Dropouts (steps > 1.5 median steps): summary and the [t_before, t_after] gap pairs."""
    dt = np.diff(t)
    med = float(np.median(dt))
    idx = np.flatnonzero(dt > 1.5 * med)
    missing = int(np.sum(np.round(dt[idx] / med) - 1))
    gaps = [[float(t[i]), float(t[i + 1])] for i in idx]
    return {"count": int(idx.size), "missing_samples": missing, "at_s": [g[0] for g in gaps]}, gaps


def read_fusion_csv(path: Path, cols: list, data: np.ndarray) -> Session:
    """Session from a Fusion-style x-io CSV (time, gyroscope, accelerometer, magnetometer columns).

    Args:
        path: the file (for messages and the name).
        cols, data: the parsed table (see `read_csv_table`).
    Returns:
        Session in SI units, held magnetometer copies set to NaN.
    Raises:
        SessionError: missing columns or unknown units.
    """
    src = str(path)
    spec = parse_xio_header(cols)
    converted: list = []
    ti, tu = spec["t"]
    t = data[:, ti] * _TIME_SCALE[tu]
    gyr = _block(src, spec, data, "gyr", converted)
    acc = _block(src, spec, data, "acc", converted)
    if ("mag", "x") not in spec and path.name == "Inertial.csv":
        raise SessionError(src, "Magnetometer X", "an x-IMU3 Inertial.csv alone (no magnetometer)",
                           "the x-IMU3 folder holding Inertial.csv and Magnetometer.csv")
    mag, held = drop_held_rows(_block(src, spec, data, "mag", converted))
    duration = float(t[-1] - t[0]) if t.size > 1 else 0.0
    n_mag = int(np.sum(np.all(np.isfinite(mag), axis=1)))
    meta = {"format": "xio-csv", "converted": converted, "mag_unit": spec[("mag", "x")][1], "mag_held": held,
            "mag_rate_hz": n_mag / duration if duration > 0 else 0.0}
    return Session(t=t - (t[0] if t.size else 0.0), gyr=gyr, acc=acc, mag=mag, source=src,
                   name=path.stem, meta=meta)


def _nearest(t_ref: np.ndarray, t_q: np.ndarray) -> np.ndarray:
    """Index into sorted t_ref of the sample nearest to each t_q."""
    j = np.clip(np.searchsorted(t_ref, t_q), 1, len(t_ref) - 1)
    left_closer = (t_q - t_ref[j - 1]) <= (t_ref[j] - t_q)
    return np.where(left_closer, j - 1, j)


def _place_mag(t: np.ndarray, t_mag: np.ndarray, mag: np.ndarray) -> tuple[np.ndarray, int]:
    """Put each magnetometer sample on the nearest inertial sample (within half a step)."""
    out = np.full((t.size, 3), np.nan)
    half = 0.5 * float(np.median(np.diff(t)))
    j = _nearest(t, t_mag)
    ok = np.abs(t[j] - t_mag) <= half
    j_ok, rows = j[ok], np.flatnonzero(ok)
    _, first = np.unique(j_ok, return_index=True)     # two samples on one slot: keep the first
    out[j_ok[first]] = mag[rows[first]]
    return out, int(t_mag.size - first.size)


QUAT_SOURCE = "x-IMU3 onboard AHRS (estimate, not ground truth)"


def read_ximu3_folder(path: Path) -> Session:
    """Session from an x-IMU3 export folder (Inertial.csv + Magnetometer.csv, optional Quaternion.csv).

    Args:
        path: the folder.
    Returns:
        Session on the inertial time stamps (s from the first), SI units, magnetometer in its own
        unit (a.u.) on the nearest inertial samples, onboard AHRS quaternion (not ground truth) in
        `quat` when Quaternion.csv shares the inertial time stamps.
    Raises:
        SessionError: missing files or columns, unsorted time stamps.
    """
    src = str(path)
    ts, gyr, acc, tm, mag_raw, held, converted, mag_unit = read_ximu3_tables(path)
    t0 = ts[0] if ts.size else 0.0
    t, tm = ts - t0, tm - t0
    meta = {"format": "x-imu3", "converted": converted, "mag_unit": mag_unit, "mag_held": held}
    if t.size >= 2 and np.all(np.diff(t) > 0):
        keep = np.all(np.isfinite(mag_raw), axis=1)
        mag, unplaced = _place_mag(t, tm[keep], mag_raw[keep])
        meta["dropouts"], meta["gaps"] = _dropouts(t)
        meta["mag_unplaced"] = unplaced
    else:
        mag = np.full((t.size, 3), np.nan)   # validation reports the time stamps
    quat = _onboard_quat(path, ts)
    if quat is not None:
        meta["quat_source"] = QUAT_SOURCE
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=quat, source=src, name=path.name, meta=meta)


def read_ximu3_tables(path: Path) -> tuple:
    """(inertial stamps s, gyr, acc, magnetometer stamps s, magnetometer with held rows NaN, held rows, converted,
    magnetometer unit) of an x-IMU3 folder, stamps absolute (the device clock), SI units (`read_ximu3_folder`)."""
    src = str(path)
    for name in ("Inertial.csv", "Magnetometer.csv"):
        if not (path / name).is_file():
            raise SessionError(src, name, "file missing", "an x-IMU3 folder with Inertial.csv and Magnetometer.csv")
    cols, data = read_csv_table(path / "Inertial.csv")
    spec = parse_xio_header(cols)
    if "t" not in spec:
        raise SessionError(str(path / "Inertial.csv"), "Timestamp", "column missing", "'Timestamp (us)'")
    converted: list = []
    ts = data[:, spec["t"][0]] * _TIME_SCALE[spec["t"][1]]
    gyr = _block(str(path / "Inertial.csv"), spec, data, "gyr", converted)
    acc = _block(str(path / "Inertial.csv"), spec, data, "acc", converted)
    mcols, mdata = read_csv_table(path / "Magnetometer.csv")
    mspec = parse_xio_header(mcols, quantity="mag")
    if "t" not in mspec:
        raise SessionError(str(path / "Magnetometer.csv"), "Timestamp", "column missing", "'Timestamp (us)'")
    tm = mdata[:, mspec["t"][0]] * _TIME_SCALE[mspec["t"][1]]
    mag_raw, held = drop_held_rows(_block(str(path / "Magnetometer.csv"), mspec, mdata, "mag", converted))
    return ts, gyr, acc, tm, mag_raw, held, converted, mspec[("mag", "x")][1]


def _onboard_quat(path: Path, ts: np.ndarray) -> Optional[np.ndarray]:
    """Quaternion.csv (w,x,y,z) when it shares the inertial time stamps, else None."""
    if not (path / "Quaternion.csv").is_file():
        return None
    cols, data = read_csv_table(path / "Quaternion.csv")
    if data.shape[0] != ts.size or data.shape[1] < 5 or not np.array_equal(data[:, 0] * 1e-6, ts):
        return None
    return data[:, 1:5]
