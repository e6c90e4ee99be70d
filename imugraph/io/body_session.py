"""Multi-IMU (body) sessions: one in-memory type, the project's own folder format, reader dispatch.

Own format (a folder):

    session.json   {"format": "imugraph-body", "version": 1, "name": str,
                    "sensors": {segment: "<file>.npz", ...},       # one single-IMU NPZ per sensor
                    "skeleton": {"names", "parents", "offsets", "sensed", "ends"} | null,
                    "truth": "truth.npz" | null, "meta": {...},
                    "gyr_robust_max": {segment: rad/s}}              # simulated sessions only (`read_own_folder`)
    <segment>.npz  single-IMU NPZ contract (DESIGN.md): gyr, acc, mag, t (and quat when known); mag may be
                   missing or all NaN (a 6-axis IMU)
    truth.npz      optional: n_quat (T,S,4), n_pos (T,S,3), names (S,), placement_names (P,),
                   bRs (P,3,3), b_pos (P,3), and sensor_pos, sensor_vel (P,T,3) when known

All sensors share the sample times t. Every file is written atomically; session.json last, so a
folder without it is incomplete. Other formats read into the same `BodySession`: the gaittoolbox
Xsens MTw export (`imugraph.io.gaittoolbox`), MVNX (`imugraph.io.mvnx`) and a folder of x-IMU3 export folders
(`imugraph.io.xio_body`).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np

from imugraph.body.skeleton import Skeleton
from imugraph.errors import SessionError
from imugraph.io.session import Session
from imugraph.io.validate import gyr_robust_max     # the units check's statistic, recorded for simulations
from imugraph.io.writers import atomic_write_bytes, atomic_write_text, json_ready

PathLike = Union[str, Path]
FORMAT = "imugraph-body"


@dataclass(frozen=True)
class BodySession:
    """Several IMUs on one body, sampled at common times.

    Attributes:
        t: (N,) common sample times, s.
        sensors: segment name → that sensor's single-IMU Session (same t).
        skeleton: the body model, when the source defines one.
        truth: optional {"n_quat": (N,S,4), "n_pos": (N,S,3), "names": [...], "placements":
            {segment: {"bRs": (3,3), "b_pos": (3,)}}, "sensor_pos"/"sensor_vel": {segment: (N,3)}}.
        source: where it was read from; name: short name; meta: reader details.
    """

    t: np.ndarray
    sensors: dict
    skeleton: Optional[Skeleton] = None
    truth: Optional[dict] = None
    source: str = "<memory>"
    name: str = "body"
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def rate(self) -> float:
        return float(1.0 / np.median(np.diff(self.t)))

    def slice(self, start: int, stop: int) -> "BodySession":
        """Samples [start, stop) of every sensor and of the truth."""
        s = slice(start, stop)
        truth = None
        if self.truth is not None:
            truth = dict(self.truth)
            for k in ("n_quat", "n_pos"):
                if k in truth:
                    truth[k] = np.asarray(truth[k])[s]
            for key in ("sensor_pos", "sensor_vel"):
                if key in truth:
                    truth[key] = {k: np.asarray(v)[s] for k, v in truth[key].items()}
        return BodySession(self.t[s], {k: v.slice(start, stop) for k, v in self.sensors.items()},
                           self.skeleton, truth, self.source, self.name, dict(self.meta))


def skeleton_to_dict(skel: Skeleton) -> dict:
    return {"names": list(skel.names), "parents": list(skel.parents), "offsets": skel.offsets.tolist(),
            "sensed": list(skel.sensed), "ends": skel.ends.tolist()}


def skeleton_from_dict(src: str, d: dict) -> Skeleton:
    try:
        return Skeleton(names=tuple(d["names"]), parents=tuple(d["parents"]), offsets=np.array(d["offsets"], float),
                        sensed=tuple(d["sensed"]), ends=np.array(d["ends"], float))
    except (KeyError, TypeError, ValueError) as exc:
        raise SessionError(src, "skeleton", f"malformed ({exc})", "names, parents, offsets, sensed, ends") from None
    except SessionError as exc:
        raise SessionError(src, f"skeleton.{exc.field}", exc.found, exc.expected) from None


def _npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def write_body_session(folder: PathLike, session: BodySession) -> Path:
    """Write `session` in the own folder format (module docstring), atomically file by file.

    Returns:
        The folder.
    """
    folder = Path(folder)
    files = {}
    for seg, s in session.sensors.items():
        arrays = {"t": s.t, "gyr": s.gyr, "acc": s.acc, "mag": s.mag}
        if s.quat is not None:
            arrays["quat"] = s.quat
        files[seg] = f"{seg}.npz"
        atomic_write_bytes(folder / files[seg], _npz_bytes(**arrays))
    truth_file = None
    if session.truth is not None:
        tr = session.truth
        place = tr.get("placements", {}) or {}
        pn = list(place)
        arrays = {"n_quat": np.asarray(tr["n_quat"], float), "n_pos": np.asarray(tr["n_pos"], float),
                  "names": np.array(tr["names"], dtype=str), "placement_names": np.array(pn, dtype=str),
                  "bRs": np.array([place[n]["bRs"] for n in pn], float).reshape(-1, 3, 3),
                  "b_pos": np.array([place[n]["b_pos"] for n in pn], float).reshape(-1, 3)}
        for key in ("sensor_pos", "sensor_vel"):
            if tr.get(key):
                arrays[key] = np.array([tr[key][n] for n in pn], float)
        truth_file = "truth.npz"
        atomic_write_bytes(folder / truth_file, _npz_bytes(**arrays))
    doc = {"format": FORMAT, "version": 1, "name": session.name, "sensors": files,
           "skeleton": None if session.skeleton is None else skeleton_to_dict(session.skeleton),
           "truth": truth_file, "meta": session.meta}
    if session.meta.get("simulated"):   # what the writer wrote: the reader's units check trusts these files only
        doc["gyr_robust_max"] = {seg: gyr_robust_max(s.gyr) for seg, s in session.sensors.items()}
    atomic_write_text(folder / "session.json", json.dumps(json_ready(doc), indent=1) + "\n")
    return folder


def _read_truth(path: Path) -> dict:
    src = str(path)
    try:
        z = np.load(path, allow_pickle=False)
        names = [str(n) for n in z["names"]]
        pn = [str(n) for n in z["placement_names"]]
        truth = {"n_quat": z["n_quat"], "n_pos": z["n_pos"], "names": names,
                 "placements": {n: {"bRs": z["bRs"][i], "b_pos": z["b_pos"][i]} for i, n in enumerate(pn)}}
        for key in ("sensor_pos", "sensor_vel"):
            if key in z.files:
                truth[key] = {n: z[key][i] for i, n in enumerate(pn)}
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise SessionError(src, "truth", f"unreadable ({str(exc)[:80]})",
                           "n_quat, n_pos, names, placement_names, bRs, b_pos arrays") from None
    return truth


def _unique_keys(src: str):
    """json object_pairs_hook refusing a key given twice (json.loads would keep the last one silently)."""
    def hook(pairs: list) -> dict:
        seen = set()
        for k, _ in pairs:
            if k in seen:
                raise SessionError(src, k, "the key twice in one object", "each key once")
            seen.add(k)
        return dict(pairs)
    return hook


def _check_segments(src: str, sensors_doc: dict, skel: Optional[Skeleton]) -> None:
    """The segment names of session.json's "sensors" against its skeleton (read before any sensor file): every
    name a segment of the skeleton, every sensed segment given a sensor. Without a skeleton `default_skeleton`
    checks the names."""
    if skel is None:
        return
    unknown = [seg for seg in sensors_doc if seg not in skel.names]
    if unknown:
        raise SessionError(src, "sensors", f"unknown segment{'s' if len(unknown) > 1 else ''} {unknown}",
                           f"segments of the session's skeleton: {', '.join(skel.names)}")
    missing = [seg for seg in skel.sensed if seg not in sensors_doc]
    if missing:
        raise SessionError(src, "sensors", f"no sensor file for the sensed segment{'s' if len(missing) > 1 else ''} "
                           f"{missing}", f"one file for each of the skeleton's sensed segments {list(skel.sensed)}")


def _sensor_files(folder: Path, src: str, sensors_doc: dict) -> dict:
    """{segment: path} of session.json's "sensors", refusing one file given to two segments (the same IMU
    twice: mocap then solves two segments from one sensor's readings)."""
    paths, first = {}, {}
    for seg, fname in sensors_doc.items():
        if not isinstance(fname, str) or not fname:
            raise SessionError(src, f"sensors.{seg}", repr(fname)[:60], "a file name (<segment>.npz)")
        p = folder / fname
        key = p.resolve()
        if key in first:
            raise SessionError(src, f"sensors.{seg}", f"'{fname}', the file of '{first[key]}' too",
                               "one NPZ file per segment")
        first[key], paths[seg] = seg, p
    return paths


def read_own_folder(folder: PathLike) -> BodySession:
    """Read the own folder format (module docstring).

    A sensor NPZ without 'mag', or with mag all NaN, is a 6-axis IMU: read with mag all NaN, listed in
    ``meta["no_mag"]`` (mocap runs without magnetometers by default and refuses --mag on it). A simulated session
    (meta "simulated") skips the saturation check (noise-free simulations hold exact plateaus) and, for a sensor
    file whose robust max |gyr| is the one the writer recorded ("gyr_robust_max"), the units check: the
    simulator's segment rates add up along the chain and may exceed any real gyroscope's range (35 rad/s).

    Raises:
        SessionError: missing/invalid session.json (a key given twice included), one file for two segments,
        segment names not in the skeleton (naming the valid ones), a sensed segment without a file, a sensor file
        that is not a valid NPZ session, sensors with different sample times.
    """
    from imugraph.io.readers import read_npz
    from imugraph.io.validate import validate_session

    folder = Path(folder)
    src = str(folder / "session.json")
    try:
        doc = json.loads((folder / "session.json").read_text(encoding="utf-8"), object_pairs_hook=_unique_keys(src))
    except FileNotFoundError:
        raise SessionError(src, "file", "no such file", "a body-session folder with session.json") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SessionError(src, "file", f"unreadable or invalid JSON ({str(exc)[:80]})", "a JSON object") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise SessionError(src, "format", repr(doc.get("format") if isinstance(doc, dict) else doc)[:60], repr(FORMAT))
    sensors_doc = doc.get("sensors")
    if not isinstance(sensors_doc, dict) or not sensors_doc:
        raise SessionError(src, "sensors", repr(sensors_doc)[:60], "an object {segment: file.npz}")
    paths = _sensor_files(folder, src, sensors_doc)
    skel = None if doc.get("skeleton") is None else skeleton_from_dict(src, doc["skeleton"])
    _check_segments(src, sensors_doc, skel)
    sensors, t, no_mag = {}, None, []
    meta = doc.get("meta") if isinstance(doc.get("meta"), dict) else {}
    simulated = bool(meta.get("simulated"))
    written = doc.get("gyr_robust_max") if simulated and isinstance(doc.get("gyr_robust_max"), dict) else {}
    for seg, path in paths.items():
        raw = read_npz(path, mag_optional=True)
        skip = ["saturation"] if simulated else []
        if np.isnan(np.asarray(raw.mag, float)).all():      # no magnetometer (±inf still checked): nothing to check
            skip.append("mag")
            no_mag.append(seg)
        w = written.get(seg)
        if isinstance(w, (int, float)) and np.isclose(gyr_robust_max(raw.gyr), w, rtol=1e-12, atol=0.0):
            skip.append("units")                      # the simulator's own rad/s, as written
        s = validate_session(raw, skip=tuple(skip))
        s = Session(s.t, s.gyr, s.acc, s.mag, s.quat, s.movement, s.source, seg, s.meta)
        if t is None:
            t = s.t
        elif s.t.shape != t.shape or np.max(np.abs(s.t - t)) > 1e-9:
            raise SessionError(str(path), "t", f"{s.n} samples differing from the first sensor's",
                               f"the same {t.size} sample times for every sensor")
        sensors[seg] = s
    if skel is None:
        skel = default_skeleton(src, sensors)
    truth = None if not doc.get("truth") else _read_truth(folder / str(doc["truth"]))
    meta = dict(meta, no_mag=no_mag) if no_mag else dict(meta)
    return BodySession(t=t, sensors=sensors, skeleton=skel, truth=truth, source=str(folder),
                       name=str(doc.get("name", folder.name)), meta=meta)


def default_skeleton(src: str, sensors: dict) -> Skeleton:
    """The nominal (1.75 m) MVN full body when the sensors are its 17 sensed segments, the 7-segment lower
    body when they are its 7; anything else needs a skeleton in session.json."""
    from imugraph.body.skeleton import FULL_BODY_SENSED, LOWER_BODY, full_body, lower_body

    names = set(sensors)
    if names == set(FULL_BODY_SENSED):
        return full_body(1.75)
    if names == set(LOWER_BODY):
        return lower_body(1.75)
    raise SessionError(src, "skeleton", f"null with sensors {sorted(names)}",
                       "a skeleton, or exactly the 17 full-body or 7 lower-body MVN segments")


def is_body_session(path: PathLike) -> bool:
    """A path `read_body_session` is meant for (an .mvnx path by its suffix alone)."""
    from imugraph.io.xio_body import is_ximu3_body_folder

    p = Path(path)
    if p.is_dir():
        return (p / "session.json").exists() or any(p.glob("*_00B4*.txt")) or is_ximu3_body_folder(p)
    return p.suffix.lower() == ".mvnx"


def read_body_session(path: PathLike) -> BodySession:
    """Any multi-IMU session: own folder (session.json), gaittoolbox MTw folder (*_<id>.txt), .mvnx, a folder
    of x-IMU3 export folders (`imugraph.io.xio_body.read_ximu3_body`), or the qmt full-body .mat
    (`imugraph.io.qmt_body.read_qmt_body`).

    Raises:
        SessionError: a path that is none of these.
    """
    p = Path(path)
    if p.is_dir() and (p / "session.json").exists():
        return read_own_folder(p)
    if p.is_dir() and any(p.glob("*_00B4*.txt")):
        from imugraph.io.gaittoolbox import read_gaittoolbox
        return read_gaittoolbox(p)
    if p.is_file() and p.suffix.lower() == ".mvnx":
        from imugraph.io.mvnx import read_mvnx
        return read_mvnx(p)
    from imugraph.io.xio_body import is_ximu3_body_folder, read_ximu3_body
    if is_ximu3_body_folder(p):                       # one x-IMU3 export folder per sensor
        return read_ximu3_body(p)
    from imugraph.io.qmt_body import is_qmt_body_mat, read_qmt_body
    if is_qmt_body_mat(p):                            # the qmt full-body .mat (t + one struct per sensor)
        return read_qmt_body(p)
    raise SessionError(str(p), "path", "not a body-session folder, an Xsens MTw folder, a folder of x-IMU3 folders, "
                       "a qmt full-body .mat or an .mvnx file", "a folder with session.json, a gaittoolbox rawimu "
                       "folder, a folder of x-IMU3 export folders, a qmt full-body .mat (t and one struct per sensor "
                       "with acc, gyr, quat), or an .mvnx file")


def read_gaittoolbox(folder: PathLike) -> BodySession:
    """See `imugraph.io.gaittoolbox.read_gaittoolbox`."""
    from imugraph.io.gaittoolbox import read_gaittoolbox as _read
    return _read(folder)


def read_gaittoolbox_vicon(path: PathLike) -> dict:
    """See `imugraph.io.gaittoolbox.read_gaittoolbox_vicon`."""
    from imugraph.io.gaittoolbox import read_gaittoolbox_vicon as _read
    return _read(path)


def read_mvnx(path: PathLike) -> BodySession:
    """See `imugraph.io.mvnx.read_mvnx`."""
    from imugraph.io.mvnx import read_mvnx as _read
    return _read(path)
