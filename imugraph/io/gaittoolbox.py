"""The gaittoolbox sample (UNSW NeuRA, subject S02): 7 Xsens MTw on the lower body, and Vicon.

`read_gaittoolbox(folder)`: the MT Manager exports ``<trial>-000_<sensor id>.txt`` of a ``rawimu``
folder (each read by `imugraph.io.xsens.read_xsens_mtw`), put on MVN segment names by the sensor ids
of ../shared/data/README.md (`SENSOR_IDS`; the two extra copies C49, C4A are ignored). The sensors are
synchronised by the Awinda station: they are aligned on their PacketCounter (the common range kept).

`read_gaittoolbox_vicon(csv)`: ``vicon/<trial>.csv`` — ``// key=value`` header lines (fs, frame, posUnit,
idx), one column line, then per frame the joint centres (PELV, L/R FEP hip, FEO knee, TIO ankle, TOE;
``_1.._3`` = x, y, z in m, Vicon world frame, z up) and segment quaternions (qRPV pelvis, qR/LTH thigh,
qR/LSK shank, qR/LFT foot; ``_1.._4`` = w, x, y, z, segment → Vicon world as in the file). The frames
cover IMU samples startFrame..endFrame (1-based, inclusive) of ``data-list.csv`` beside the trial folders.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Union

import numpy as np

from imugraph.body.skeleton import LOWER_BODY, lower_body, skeleton_from_spec
from imugraph.errors import SessionError
from imugraph.io.body_session import BodySession
from imugraph.io.session import Session
from imugraph.io.xsens import column_delimiter, read_xsens_mtw, to_commas

PathLike = Union[str, Path]
SENSOR_IDS = {"Pelvis": "00B40B91", "LeftUpperLeg": "00B40C45", "RightUpperLeg": "00B40C3C",
              "LeftLowerLeg": "00B40C44", "RightLowerLeg": "00B40C47", "LeftFoot": "00B40C55",
              "RightFoot": "00B40C48"}
VICON_QUATS = {"Pelvis": "qRPV", "RightUpperLeg": "qRTH", "LeftUpperLeg": "qLTH", "RightLowerLeg": "qRSK",
               "LeftLowerLeg": "qLSK", "RightFoot": "qRFT", "LeftFoot": "qLFT"}
VICON_JOINTS = ("PELV", "LFEP", "LFEO", "LTIO", "LTOE", "RFEP", "RFEO", "RTIO", "RTOE")
_FILE = re.compile(r"^(?P<trial>.+)-\d{3}_(?P<id>[0-9A-Fa-f]{8})\.txt$")


def _first_counter(path: Path) -> int:
    """PacketCounter of the first data row (after the // header and the column line)."""
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        rows = (ln for ln in fh if not ln.startswith("//"))
        line = next(rows, "")
        delim = column_delimiter(line)
        cols = [c.strip() for c in line.strip().split(delim)]
        first = to_commas([next(rows, "").strip()], delim)[0].split(",")
    try:
        return int(float(first[cols.index("PacketCounter")]))
    except (ValueError, IndexError):
        raise SessionError(str(path), "PacketCounter", f"first row {first[:2]}", "an integer packet counter") from None


def read_gaittoolbox(folder: PathLike, trial: str | None = None, skeleton=None) -> BodySession:
    """The 7 lower-body MTw of one trial as a BodySession on `lower_body()` (nominal 1.75 m proportions).

    Args:
        folder: the ``rawimu`` folder.
        trial: trial prefix (e.g. 'S02-Trial-Walk-1'); None: the only one present.
        skeleton: None (default: `lower_body(1.75)`), a Skeleton with the 7 segments, or a spec string of
            `imugraph.body.skeleton.skeleton_from_spec` ('bvh:PATH': the subject's dimensions from a BVH
            HIERARCHY, e.g. the trial's own Xsens MVN export).
    Returns:
        BodySession (t from 0 s, sensors keyed by MVN segment; each Session's quat is the MTw's onboard
        estimate, not ground truth; truth None).
    Raises:
        SessionError: no or several trials, a missing sensor, sensors that do not overlap in time.
    """
    folder = Path(folder)
    found = {}
    for f in sorted(folder.glob("*.txt")):
        m = _FILE.match(f.name)
        if m:
            found.setdefault(m["trial"], {})[m["id"].upper()] = f
    if trial is None:
        if len(found) != 1:
            raise SessionError(str(folder), "files", f"trials {sorted(found)}",
                               "exactly one trial of <trial>-000_<sensor id>.txt files (or pass trial=)")
        trial = next(iter(found))
    files = found.get(trial, {})
    missing = [f"{seg} ({sid})" for seg, sid in SENSOR_IDS.items() if sid not in files]
    if missing:
        raise SessionError(str(folder), "sensors", f"no file for {missing}", f"{trial}-000_<id>.txt for all 7 sensors")
    sessions = {seg: read_xsens_mtw(files[sid]) for seg, sid in SENSOR_IDS.items()}
    start = {seg: _first_counter(files[sid]) for seg, sid in SENSOR_IDS.items()}
    # align on PacketCounter: keep the common range (unwrapped counters relative to each first row)
    c0 = max(start.values())
    rate = sessions["Pelvis"].meta.get("rate_hz") or sessions["Pelvis"].rate
    lo = {seg: int(round(c0 - start[seg])) for seg in sessions}
    n = min(s.n - lo[seg] for seg, s in sessions.items())
    if n < 2:
        raise SessionError(str(folder), "PacketCounter", f"first counters {start}", "sensors recording together")
    sensors = {}
    for seg, s in sessions.items():
        part = s.slice(lo[seg], lo[seg] + n)
        _check_finite(seg, part, lo[seg])
        sensors[seg] = Session(part.t - part.t[0], part.gyr, part.acc, part.mag, part.quat, None,
                               part.source, seg, dict(part.meta, sensor_id=SENSOR_IDS[seg]))
    t = sensors["Pelvis"].t
    skel, how = _skeleton(skeleton)
    meta = {"format": "gaittoolbox-rawimu", "trial": trial, "rate_hz": rate, "sensor_ids": dict(SENSOR_IDS),
            "first_packet": c0, "skeleton": how}
    return BodySession(t=t, sensors=sensors, skeleton=skel, truth=None, source=str(folder),
                       name=trial, meta=meta)


def _check_finite(seg: str, part: Session, offset: int) -> None:
    """gyr and acc of one sensor's common range finite, else SessionError naming the file, the sensor, the
    sample index and time of the first non-finite run (t from the trial's common start) and the file's data row."""
    from imugraph.io.validate import runs

    for ch, col in (("gyr", "Gyr_X..Z"), ("acc", "Acc_X..Z")):
        x = np.asarray(getattr(part, ch), float)
        bad = ~np.all(np.isfinite(x), axis=1)
        if not bad.any():
            continue
        start, stop = runs(bad)
        a, b = int(start[0]), int(stop[0]) - 1
        t = part.t - part.t[0]
        raise SessionError(part.source, f"sensors[{seg}].{ch}", f"empty or non-finite {col} in {int(bad.sum())} "
                           f"samples; first run at samples {a}..{b} (t = {t[a]:.2f}..{t[b]:.2f} s, data rows "
                           f"{a + offset + 1}..{b + offset + 1} of the file)", "finite values in every sample")


def _skeleton(skeleton) -> tuple:
    """(Skeleton, description) for `read_gaittoolbox`'s skeleton argument."""
    if isinstance(skeleton, str) and skeleton.startswith("bvh:"):
        return (skeleton_from_spec(skeleton, LOWER_BODY),
                f"from the BVH hierarchy {skeleton[4:]} (its OFFSETs, not its motion)")
    if skeleton is None or isinstance(skeleton, str):
        skel = skeleton_from_spec(skeleton, LOWER_BODY)
        if skel is None:
            return lower_body(1.75), "lower_body(1.75) nominal proportions (subject's not known)"
        return skel, f"full_body({skeleton[7:]}) proportions"
    missing = [s for s in LOWER_BODY if s not in getattr(skeleton, "names", ())]
    if missing:
        raise SessionError("skeleton", "names", f"no segment {missing}", f"a Skeleton with {list(LOWER_BODY)}")
    return skeleton, "given skeleton"


def _data_list(path: Path, trial: str) -> tuple[int, int] | None:
    """(startFrame, endFrame) of `trial` ('S02-Trial-Walk-1') from data-list.csv, or None."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                if f"{row.get('subj', '')}-{row.get('act', '')}" == trial:
                    return int(row["startFrame"]), int(row["endFrame"])
    except (OSError, KeyError, ValueError):
        raise SessionError(str(path), "startFrame", "unreadable row", "subj,act,startFrame,endFrame") from None
    return None


def read_gaittoolbox_vicon(path: PathLike) -> dict:
    """Vicon joint centres and segment quaternions of one gaittoolbox trial (module docstring).

    Returns:
        {"t": (N,) s on the IMU time base (imu_index / fs), "imu_index": (N,) 0-based IMU samples,
         "fs": Hz, "joints": {PELV, LFEP, …: (N, 3) m}, "quat": {MVN segment: (N, 4) w,x,y,z},
         "quat_columns": {MVN segment: file prefix}, "frame": str, "source": str}
    Raises:
        SessionError: missing columns, ragged rows, frame count not matching the sample range.
    """
    path = Path(path)
    src = str(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise SessionError(src, "file", f"unreadable ({exc.strerror or exc})", "a gaittoolbox vicon csv") from None
    header = {}
    i = 0
    while i < len(lines) and lines[i].startswith("//"):
        for key, value in re.findall(r"(\w+)=(\S+)", lines[i]):
            header[key] = value
        i += 1
    if i >= len(lines):
        raise SessionError(src, "columns", "no column line", "PELV_1,PELV_2,…")
    cols = [c.strip() for c in lines[i].split(",")]
    try:
        data = np.array([[float(v) for v in ln.split(",")] for ln in lines[i + 1:] if ln.strip()])
    except ValueError:
        raise SessionError(src, "data", "a non-numeric value", "comma-separated numbers") from None
    if data.ndim != 2 or data.shape[1] != len(cols):
        raise SessionError(src, "data", f"rows of {data.shape[-1] if data.size else 0} values", f"{len(cols)} values")

    def block(prefix: str, k: int) -> np.ndarray:
        names = [f"{prefix}_{j}" for j in range(1, k + 1)]
        if any(n not in cols for n in names):
            raise SessionError(src, prefix, "columns missing", f"{names[0]}..{names[-1]}")
        return data[:, [cols.index(n) for n in names]]

    fs = float(header.get("fs", 100))
    rng = _data_list(path.parent.parent / "data-list.csv", path.stem)
    if rng is None and "idx" in header:
        rng = tuple(int(v) for v in header["idx"].split(","))
    if rng is None:
        raise SessionError(src, "idx", "no sample range (data-list.csv row or // idx= header)", "startFrame,endFrame")
    if rng[1] - rng[0] + 1 != data.shape[0]:
        raise SessionError(src, "frames", f"{data.shape[0]} frames for IMU samples {rng[0]}..{rng[1]}",
                           "one frame per IMU sample in the range")
    imu_index = np.arange(rng[0] - 1, rng[1])
    return {"t": imu_index / fs, "imu_index": imu_index, "fs": fs,
            "joints": {j: block(j, 3) for j in VICON_JOINTS},
            "quat": {seg: block(q, 4) for seg, q in VICON_QUATS.items()}, "quat_columns": dict(VICON_QUATS),
            "frame": header.get("frame", "world"), "source": src}
