"""MVNX (Xsens MVN's XML export) → BodySession.

Elements read (namespace ``http://www.xsens.com/mvn/mvnx`` or none; MVNX version 4 layout):

- ``subject/@frameRate``; ``subject/segments/segment/@label`` (segment order of the per-frame arrays)
  with ``points/point/@label`` + ``pos_b`` (point in the segment frame, m);
  ``subject/sensors/sensor/@label`` (sensor order; labels are the segments they are on);
  ``subject/joints/joint`` with ``connector1``/``connector2`` = ``Segment/pointLabel`` (parent, child).
- ``frames/frame`` with ``@type="normal"`` only (the ``identity``/``tpose``/``tpose-isb`` reference frames
  are skipped); ``@time`` in ms; children, whitespace-separated numbers per segment or sensor:
  ``orientation`` (4/segment, q0..q3 = w,x,y,z, segment → global), ``position`` (3/segment, m),
  ``sensorOrientation`` (4/sensor, sensor → global), ``sensorFreeAcceleration`` (3/sensor, m/s², global
  frame, gravity removed), ``sensorMagneticField`` (3/sensor, a.u., sensor frame); when present also
  ``sensorAngularVelocity`` (3/sensor, rad/s, sensor frame) and ``sensorAcceleration`` (3/sensor, m/s²,
  sensor frame), which older exports hold.

Per sensor, the Session's readings are (MVN 2019+ exports no raw gyroscope/accelerometer):

    acc = nRsᵀ (a_free − n_grav),  n_grav = [0, 0, −g], g = 9.81 m/s²        (unless sensorAcceleration)
    gyr_k = Log(nRs,kᵀ nRs,k+1) / Δt_k                                        (unless sensorAngularVelocity)

(imugraph.sim.body eq. P2), quat = sensorOrientation (MVN's own estimate, flagged in meta). Segment
orientations and positions are kept as `truth` (again MVN's estimate, meta["truth_source"]); the
skeleton comes from the joints' connector points: offset_child = pos_b(parent point) − pos_b(child point).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Optional, Union

import numpy as np

from imugraph.body.skeleton import Skeleton
from imugraph.errors import SessionError
from imugraph.geometry import quat_conj, quat_mul, quat_normalize, quat_to_rotmat, quat_to_rotvec
from imugraph.io.body_session import BodySession
from imugraph.io.session import Session

PathLike = Union[str, Path]
G = 9.81
_FIELDS = {"orientation": 4, "position": 3, "sensorOrientation": 4, "sensorFreeAcceleration": 3,
           "sensorMagneticField": 3, "sensorAngularVelocity": 3, "sensorAcceleration": 3}


def _tag(el: ET.Element) -> str:
    return el.tag.rsplit("}", 1)[-1]


def _numbers(src: str, text: Optional[str], what: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in (text or "").split()])
    except ValueError:
        raise SessionError(src, what, f"{(text or '')[:40]!r}", "whitespace-separated numbers") from None


def _subject(src: str, subject: ET.Element) -> tuple[list, dict, list, list, float]:
    """Segment labels, points {segment: {label: pos_b}}, sensor labels, joints [(parent/pt, child/pt)], rate."""
    segs, points, sensors, joints = [], {}, [], []
    for el in subject.iter():
        tag = _tag(el)
        if tag == "segment":
            label = el.get("label", "")
            segs.append(label)
            points[label] = {p.get("label", ""): _numbers(src, next((c.text for c in p if _tag(c) == "pos_b"), ""),
                                                          f"segment {label} point pos_b")
                             for p in el.iter() if _tag(p) == "point"}
        elif tag == "sensor":
            sensors.append(el.get("label", ""))
        elif tag == "joint":
            conn = {_tag(c): (c.text or "").strip() for c in el}
            if "connector1" in conn and "connector2" in conn:
                joints.append((conn["connector1"], conn["connector2"]))
    try:
        rate = float(subject.get("frameRate", "nan"))
    except ValueError:
        rate = float("nan")
    return segs, points, sensors, joints, rate


def _skeleton(segs: list, points: dict, sensors: list, joints: list) -> Optional[Skeleton]:
    """Skeleton from the joint connectors (None when the tree is incomplete or not rooted at segs[0])."""
    parent, offset = {}, {}
    for c1, c2 in joints:
        (s1, p1), (s2, p2) = c1.split("/", 1), c2.split("/", 1)
        if p1 not in points.get(s1, {}) or p2 not in points.get(s2, {}):
            return None
        parent[s2] = s1
        offset[s2] = points[s1][p1] - points[s2][p2]
    if any(s not in parent for s in segs[1:]) or any(parent[s] not in segs[:i + 1] for i, s in enumerate(segs) if i):
        return None
    ends = []
    for s in segs:
        kids = [offset[k] for k in segs if parent.get(k) == s]
        cands = kids or [np.asarray(p, float) for p in points[s].values() if np.size(p) == 3]
        ends.append(max(cands, key=np.linalg.norm) if cands else np.zeros(3))
    return Skeleton(names=tuple(segs), parents=tuple(-1 if i == 0 else segs.index(parent[s]) for i, s in enumerate(segs)),
                    offsets=np.array([np.zeros(3)] + [offset[s] for s in segs[1:]], float),
                    sensed=tuple(s for s in sensors if s in segs), ends=np.array(ends, float))


def read_mvnx(path: PathLike) -> BodySession:
    """Read an MVNX file (elements in the module docstring).

    Returns:
        BodySession: one Session per sensor (keyed by its label), truth = MVN segment orientations and
        positions, skeleton from the joint connectors (None when absent).
    Raises:
        SessionError: not XML, no subject, no normal frames, frames with the wrong number of values,
        missing sensorOrientation, non-increasing times.
    """
    src = str(path)
    subject, frames = None, {k: [] for k in _FIELDS}
    times = []
    try:
        for _, el in ET.iterparse(str(path), events=("end",)):
            tag = _tag(el)
            if tag == "frame":
                if el.get("type", "normal") == "normal":
                    times.append(float(el.get("time", "nan")))
                    kids = {_tag(c): c.text for c in el}
                    for key in _FIELDS:
                        frames[key].append(_numbers(src, kids[key], f"frame {len(times) - 1} {key}")
                                           if key in kids else None)
                el.clear()
            elif tag == "subject":
                subject = el
    except ET.ParseError as exc:
        raise SessionError(src, f"line {exc.position[0]}", f"malformed XML ({exc.msg})", "an MVNX file") from None
    except OSError as exc:
        raise SessionError(src, "file", f"unreadable ({exc.strerror or exc})", "a readable MVNX file") from None
    if subject is None:
        raise SessionError(src, "subject", "no <subject> element", "an MVNX file with subject/segments/sensors")
    segs, points, sensors, joints, rate = _subject(src, subject)
    if not times:
        raise SessionError(src, "frames", "no frame of type 'normal'", "recorded frames")
    if not sensors or not segs:
        raise SessionError(src, "sensors", f"{len(segs)} segments, {len(sensors)} sensors", "at least one of each")
    n_frames = len(times)
    t = (np.array(times) - times[0]) / 1000.0
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        if np.isfinite(rate) and rate > 0:
            t = np.arange(n_frames) / rate
        else:
            raise SessionError(src, "frame/@time", "missing or non-increasing times and no frameRate", "ms times")

    def stack(key: str, count: int) -> Optional[np.ndarray]:
        rows = frames[key]
        if all(r is None for r in rows):
            return None
        width = _FIELDS[key] * count
        bad = next((k for k, r in enumerate(rows) if r is None or r.size != width), None)
        if bad is not None:
            got = "missing" if rows[bad] is None else f"{rows[bad].size} values"
            raise SessionError(src, f"frame {bad} {key}", got, f"{width} values ({count} × {_FIELDS[key]})")
        return np.array(rows).reshape(n_frames, count, _FIELDS[key])

    s_q = stack("sensorOrientation", len(sensors))
    if s_q is None:
        raise SessionError(src, "sensorOrientation", "absent", "sensor orientations in every frame")
    s_q = quat_normalize(s_q)
    free, mag = stack("sensorFreeAcceleration", len(sensors)), stack("sensorMagneticField", len(sensors))
    raw_gyr, raw_acc = stack("sensorAngularVelocity", len(sensors)), stack("sensorAcceleration", len(sensors))
    if free is None and raw_acc is None:
        raise SessionError(src, "sensorFreeAcceleration", "absent", "sensorFreeAcceleration or sensorAcceleration")
    dt = np.diff(t)
    out = {}
    for i, label in enumerate(sensors):
        q = s_q[:, i]
        if raw_acc is not None:
            acc = raw_acc[:, i]
        else:
            acc = np.einsum("tba,tb->ta", quat_to_rotmat(q), free[:, i] + np.array([0.0, 0.0, G]))
        if raw_gyr is not None:
            gyr = raw_gyr[:, i]
        else:
            w = quat_to_rotvec(quat_mul(quat_conj(q[:-1]), q[1:])) / dt[:, None]
            gyr = np.vstack([w, w[-1:]])
        m = mag[:, i] if mag is not None else np.full((n_frames, 3), np.nan)
        out[label] = Session(t=t, gyr=gyr, acc=acc, mag=m, quat=q, source=src, name=label,
                             meta={"format": "mvnx", "quat_source": "Xsens MVN sensorOrientation (estimate)",
                                   "gyr_source": "sensorAngularVelocity" if raw_gyr is not None else
                                   "differentiated sensorOrientation", "acc_source": "sensorAcceleration"
                                   if raw_acc is not None else "sensorFreeAcceleration + g, to the sensor frame"})
    seg_q, seg_p = stack("orientation", len(segs)), stack("position", len(segs))
    truth = None
    if seg_q is not None and seg_p is not None:
        truth = {"n_quat": quat_normalize(seg_q), "n_pos": seg_p, "names": list(segs), "placements": {}}
    meta = {"format": "mvnx", "frame_rate": rate, "truth_source": "Xsens MVN segment estimates", "g": G}
    return BodySession(t=t, sensors=out, skeleton=_skeleton(segs, points, sensors, joints), truth=truth,
                       source=src, name=Path(path).stem, meta=meta)
