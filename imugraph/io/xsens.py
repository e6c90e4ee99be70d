"""Xsens MTw (MT Manager) text exports, as in gaittoolbox's ``rawimu/*.txt``.

Layout: header lines starting with ``//`` (``// Update Rate: 100.0Hz`` gives the rate), then a
column line (``PacketCounter,SampleTimeFine,Acc_X,…,Gyr_X,…,Mag_X,…,Quat_q0…q3``) and the data, separated
by commas, or by tabs or semicolons as MT Manager's export settings allow (the column line's separator is
used; with tabs or semicolons a decimal comma is read as a decimal point, `column_delimiter`). Units as
exported: Acc m/s², Gyr rad/s, Mag normalised a.u. (kept). Time comes from
``SampleTimeFine`` (10 kHz ticks, 32-bit wrap) when it is filled in, else from ``PacketCounter``
(16-bit wrap) divided by the update rate; missing packets are reported in ``meta["gaps"]``.
``Quat_q0..q3`` (w,x,y,z, sensor→global) is the MTw's own filter output, kept in `quat` with
``meta["quat_source"]`` saying it is an onboard estimate, not ground truth.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.io.session import Session
from imugraph.io.xio import parse_csv_lines

_RATE = re.compile(r"update\s*rate\s*:\s*([0-9.]+)\s*hz", re.I)


def column_delimiter(line: str) -> str:
    """The separator of an MT Manager column line: tab or ';' when the line holds one, else ','."""
    return "\t" if "\t" in line else (";" if ";" in line else ",")


def to_commas(lines: list, delimiter: str) -> list:
    """Data lines separated by `delimiter` as comma-separated lines with decimal points (a tab- or
    semicolon-separated export may write decimal commas: "8,696773;0,341363" → "8.696773,0.341363")."""
    if delimiter == ",":
        return lines
    return [ln.replace(",", ".").replace(delimiter, ",") for ln in lines]


def _header(path: Path) -> tuple[int, Optional[float], list, str]:
    """Number of // lines, update rate (Hz or None), column names, column delimiter."""
    n_comment, rate = 0, None
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        for line in fh:
            if not line.startswith("//"):
                delim = column_delimiter(line)
                return n_comment, rate, [c.strip() for c in line.strip().split(delim)], delim
            n_comment += 1
            m = _RATE.search(line)
            if m:
                rate = float(m.group(1))
    return n_comment, rate, [], ","


def _unwrap(counter: np.ndarray, modulus: float) -> np.ndarray:
    """Cumulative counter from a wrapping one: steps < 0 gain one modulus."""
    d = np.diff(counter)
    d = np.where(d < 0, d + modulus, d)
    return np.concatenate([[0.0], np.cumsum(d)])


def _columns(src: str, cols: list, data: np.ndarray, prefix: str, names: str) -> np.ndarray:
    idx = []
    for a in names:
        name = f"{prefix}{a}"
        if name not in cols:
            raise SessionError(src, name, "column missing", f"Xsens columns {prefix}{names[0]}..{names[-1]}")
        idx.append(cols.index(name))
    return data[:, idx]


def _time(src: str, cols: list, data: np.ndarray, rate: Optional[float]) -> tuple[np.ndarray, str]:
    if "SampleTimeFine" in cols:
        stf = data[:, cols.index("SampleTimeFine")]
        if stf.size and np.all(np.isfinite(stf)):
            return _unwrap(stf, 2.0**32) / 1e4, "SampleTimeFine"
    if "PacketCounter" not in cols:
        raise SessionError(src, "PacketCounter", "column missing", "PacketCounter or SampleTimeFine")
    if rate is None or rate <= 0:
        raise SessionError(src, "Update Rate", "no '// Update Rate: …Hz' header line",
                           "the update rate in the header (time comes from PacketCounter)")
    pc = data[:, cols.index("PacketCounter")]
    if not np.all(np.isfinite(pc)):
        i = int(np.flatnonzero(~np.isfinite(pc))[0])
        raise SessionError(src, "PacketCounter", f"an empty or non-numeric value on data row {i}", "integers")
    return _unwrap(pc, 65536.0) / rate, "PacketCounter"


def read_xsens_mtw(path: Path) -> Session:
    """Session from an Xsens MTw text export.

    Args:
        path: the .txt file.
    Returns:
        Session (rad/s, m/s², magnetometer a.u.), t from 0 s; onboard quaternion in `quat`.
    Raises:
        SessionError: no column line, missing columns, no rate, malformed rows.
    """
    src = str(path)
    n_comment, rate, cols, delim = _header(path)
    if not cols or "Acc_X" not in cols:
        found = f"column line {', '.join(cols)[:80]!r}" if cols else "no column line"
        raise SessionError(src, "Acc_X", f"{found} after the // header",
                           "a line PacketCounter,SampleTimeFine,Acc_X,… (MT Manager export; comma-, tab- or "
                           "semicolon-separated)")
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        lines = fh.read().splitlines()[n_comment:]
    data = parse_csv_lines(src, cols, to_commas(lines[1:], delim), first_line=n_comment + 2)
    t, time_source = _time(src, cols, data, rate)
    gyr = _columns(src, cols, data, "Gyr_", "XYZ")
    acc = _columns(src, cols, data, "Acc_", "XYZ")
    mag = _columns(src, cols, data, "Mag_", "XYZ")
    quat = _columns(src, cols, data, "Quat_q", "0123") if "Quat_q0" in cols else None
    meta = {"format": "xsens-mtw", "converted": [], "mag_unit": "a.u. (normalised)",
            "time_source": time_source, "rate_hz": rate}
    if delim != ",":
        meta["delimiter"] = delim
    if time_source == "PacketCounter" and t.size > 1:
        step = np.diff(t) * rate
        lost = np.flatnonzero(step > 1.5)
        meta["missing_packets"] = int(np.sum(np.round(step[lost]) - 1))
        meta["gaps"] = [[float(t[i]), float(t[i + 1])] for i in lost]
    if quat is not None:
        meta["quat_source"] = "Xsens onboard filter (estimate, not ground truth)"
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=quat, source=src, name=path.stem, meta=meta)

