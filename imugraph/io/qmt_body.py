"""The qmt full-body example recording (`qmt_full_body/full_body_example_data.mat`, 16 IMUs) as a `BodySession`.

File (MATLAB v5, written by scipy; qmt, TU Berlin, MIT): a vector ``t`` (N×1, s) and one struct per sensor,
``foot_left … upper_arm_right``, ``hip``, ``lower_back``, ``upper_back``, ``head``, each with fields ``acc``
(N×3), ``gyr`` (N×3) and ``quat`` (N×4). No magnetometer, no ground truth. What the numbers are, measured on
the file (docs/formats.md "Session 22"; tests/test_qmt_body.py checks each):

- ``t``: 40.00 … 139.99 s, steps of exactly 0.01 s (100 Hz; a cut from a longer recording, kept as it is).
- ``acc`` m/s² (median |acc| standing still 9.83–10.13 over the 16 sensors: not g), ``gyr`` rad/s (at rest std
  0.002–0.046 rad/s per axis, peaks 27 rad/s on the legs: not °/s). Nothing is converted. No NaN.
- ``quat``: scalar first (w, x, y, z), unit norm, the orientation of a frame b FIXED TO THE SEGMENT but NOT the
  sensor's acc/gyr axes, into a z-up navigation frame. Shown by the gyroscope: the body-side increment of the
  quaternion, ω_b,k = 2·vec(q_{k−1}* ⊗ q_k)/Δt, equals a constant rotation C of the gyroscope sample,

      q_k = q_{k−1} ⊗ Exp(C·ω_k Δt),   C = bRs (constant per sensor, 91–162° from I)              (Q1)

  (median residual 0.022–0.071 rad/s over the 16 sensors, samples turning faster than 0.5 rad/s; read scalar
  last, the same fit leaves more than 3× that), and by gravity: nRb·C·acc standing still (1–4 s after the start;
  qmt's filter settles in its first second) is +9.8 ẑ to 0.20–1.07° (median per sensor).
  So the file's quaternion is qmt's own SEGMENT orientation estimate — another estimator, not truth.

Each sensor's Session.quat is that estimate turned into the sensor frame with the C fitted by (Q1),

    nRs = nRb_file · C                                                                            (Q2)

(least squares over the samples turning faster than 0.5 rad/s, Kabsch; C and the fit's residual are in
``meta["sensors"][segment]``; ``meta["quat_source"]`` says it is an estimate). A sensor whose (Q1) residual
exceeds `QUAT_FIT_MAX_RAD_S` gets quat None (and the reason in its meta) instead of a wrong reference.

Segments (`SEGMENTS`): hip → Pelvis, upper_back → T8, head → Head, upper_arm/forearm/hand → {Right,Left}
UpperArm/ForeArm/Hand, upper_leg/lower_leg/foot → {Right,Left}UpperLeg/LowerLeg/Foot, lower_back → L5 (`LOWER_BACK`).
Why L5 and not L3 (benchmarks/qmt_full_body.py, both solved, docs/results_issue4.md "Session 22, helper Q"): the
lower-back sensor pitches relative to the pelvis as much as the upper back does (1.11 × T8's over the 100 s), so the
lumbar bend lies BELOW it, at the L5/S1 joint that is L5's origin; and the graph's two joint centres on that sensor's
segment lie 0.29 m apart in either model, the skeleton's L5 origin → T8 origin (0.30 m), not L3 → T8 (0.20 m); joint
angles differ by < 0.2° between the two. With L5 sensed the ties (K2) give L3 = slerp(L5, T8, ⅓), T12 = slerp(L5,
T8, ⅔) (no sensed segment is tied), Pelvis–L5 is an ordinary joint, L5–T8 a lumped one. The shoulders carry no
sensor: each is tied halfway between T8 and its upper arm (K2) and the T8–upper-arm joint is lumped.
Skeleton: `imugraph.body.skeleton.full_body(height_m)` (Winter's proportions; the subject's height is not in the
file: 1.75 m nominal) with this session's sensed set, or the 7-segment lower body when only those are read.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterable, Optional, Union

import numpy as np

from imugraph.body.skeleton import LOWER_BODY, MVN_SEGMENTS, full_body, lower_body
from imugraph.errors import SessionError
from imugraph.geometry import quat_conj, quat_mul, quat_normalize, rotmat_to_quat
from imugraph.io.body_session import BodySession
from imugraph.io.session import Session

PathLike = Union[str, Path]
LOWER_BACK = "L5"
SEGMENTS = {"hip": "Pelvis", "lower_back": LOWER_BACK, "upper_back": "T8", "head": "Head",
            "upper_arm_right": "RightUpperArm", "forearm_right": "RightForeArm", "hand_right": "RightHand",
            "upper_arm_left": "LeftUpperArm", "forearm_left": "LeftForeArm", "hand_left": "LeftHand",
            "upper_leg_right": "RightUpperLeg", "lower_leg_right": "RightLowerLeg", "foot_right": "RightFoot",
            "upper_leg_left": "LeftUpperLeg", "lower_leg_left": "LeftLowerLeg", "foot_left": "LeftFoot"}
LOWER_BODY_SENSORS = tuple(k for k, v in SEGMENTS.items() if v in LOWER_BODY)
FIELDS = {"acc": 3, "gyr": 3, "quat": 4}
QUAT_FIT_MIN_RATE = 0.5           # rad/s: samples used by the (Q1) fit
QUAT_FIT_MAX_RAD_S = 0.2          # median (Q1) residual above which the file's quat is not used for that sensor
QUAT_SOURCE = "qmt full-body estimate (segment orientation turned into the sensor frame by (Q2); not truth)"


def is_qmt_body_mat(path: PathLike) -> bool:
    """A MATLAB v5 file holding ``t`` and at least two of the qmt sensor structs (checked without loading it)."""
    p = Path(path)
    if not (p.is_file() and p.suffix.lower() == ".mat"):
        return False
    import scipy.io

    try:
        names = {n for n, _, _ in scipy.io.whosmat(str(p))}
    except (OSError, ValueError, NotImplementedError, TypeError, scipy.io.matlab.MatReadError):   # v7.3, text
        return False
    return "t" in names and len(names & set(SEGMENTS)) >= 2


def _array(src: str, field: str, x, n: Optional[int], ncols: int) -> np.ndarray:
    """A numeric (n, ncols) float array, or SessionError naming the field."""
    a = np.asarray(x)
    if a.dtype.kind not in "biuf" or a.ndim != 2 or a.shape[1] != ncols or (n is not None and a.shape[0] != n):
        raise SessionError(src, field, f"shape {a.shape} dtype {a.dtype}",
                           f"a numeric ({n if n is not None else 'N'}, {ncols}) array")
    return a.astype(float)


def _struct_fields(src: str, name: str, v) -> dict:
    """{field: array} of one sensor struct as scipy.io.loadmat returns it (a (1, 1) record array)."""
    if not (isinstance(v, np.ndarray) and v.dtype.names and v.size == 1):
        raise SessionError(src, name, f"{type(v).__name__} {getattr(v, 'shape', '')} "
                           f"{getattr(v, 'dtype', '')}"[:80], "a 1×1 struct with fields acc, gyr, quat")
    rec = v.reshape(-1)[0]
    return {f: rec[f] for f in v.dtype.names}


def fit_quat_frame(quat: np.ndarray, gyr: np.ndarray, dt: float) -> tuple[np.ndarray, float, int]:
    """C = bRs of (Q1) by least squares (Kabsch) from the quaternion's body-side increments and the gyroscope.

    Returns:
        (C (3, 3), median residual |ω_b − C ω| over the samples used, rad/s; number of samples used).
    """
    q = quat_normalize(np.asarray(quat, float))
    dq = quat_mul(quat_conj(q[:-1]), q[1:])
    w_b = 2.0 * np.sign(dq[:, :1]) * dq[:, 1:] / dt                       # body-side rate of the file's frame
    w_s = np.asarray(gyr, float)[1:]                                       # q_k integrates ω_k (Q1)
    use = (np.linalg.norm(w_s, axis=1) > QUAT_FIT_MIN_RATE) & np.all(np.isfinite(w_b), axis=1)
    if use.sum() < 10:
        return np.eye(3), float("inf"), int(use.sum())
    H = w_s[use].T @ w_b[use]
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    C = Vt.T @ D @ U.T                                                     # C ω_s ≈ ω_b
    res = np.linalg.norm(w_b[use] - w_s[use] @ C.T, axis=1)
    return C, float(np.median(res)), int(use.sum())


def qmt_skeleton(segments: Iterable[str], height_m: float = 1.75):
    """`full_body(height_m)` with `segments` sensed (MVN order), or `lower_body(height_m)` for the 7 leg segments."""
    segs = set(segments)
    if segs == set(LOWER_BODY):
        return lower_body(height_m)
    return dataclasses.replace(full_body(height_m), sensed=tuple(s for s in MVN_SEGMENTS if s in segs))


def read_qmt_body(path: PathLike, sensors: Optional[Iterable[str]] = None, height_m: float = 1.75,
                  lower_back: str = LOWER_BACK) -> BodySession:
    """The qmt full-body .mat as a BodySession (module docstring).

    Args:
        path: the .mat file.
        sensors: the file's sensor names to read (e.g. `LOWER_BODY_SENSORS`); None: every known struct present.
        height_m: body height for the anthropometric skeleton, m.
        lower_back: the segment the ``lower_back`` sensor is put on, "L5" (default) or "L3" (for comparison).
    Returns:
        BodySession: t as in the file (s), sensors keyed by MVN segment (SI units, magnetometer all NaN, quat the
        (Q2) sensor-frame version of the file's estimate), truth None, skeleton `qmt_skeleton`.
    Raises:
        SessionError: not a MATLAB v5 file, ``t`` missing or not (N,) / (N, 1), no or unknown sensor structs,
            a struct without acc/gyr or with a wrong shape (naming ``<struct>.<field>``), a sensor failing
            `validate_session` (time, units, NaN runs), no ``hip`` (the root).
    """
    import scipy.io

    from imugraph.io.validate import validate_session

    p = Path(path)
    src = str(p)
    if lower_back not in ("L5", "L3"):
        raise SessionError(src, "lower_back", repr(lower_back), "'L5' or 'L3'")
    segments = dict(SEGMENTS, lower_back=lower_back)
    try:
        m = scipy.io.loadmat(src, squeeze_me=False, struct_as_record=True)
    except FileNotFoundError:
        raise SessionError(src, "file", "no such file", "the qmt full-body .mat") from None
    except (OSError, ValueError, NotImplementedError, TypeError, scipy.io.matlab.MatReadError) as exc:
        raise SessionError(src, "file", f"unreadable as MATLAB v5 ({str(exc)[:80]})", "a MATLAB v5 .mat") from None
    if "t" not in m:
        raise SessionError(src, "t", "missing", "a vector t (N×1, s)")
    t_raw = np.asarray(m["t"])
    if t_raw.dtype.kind not in "biuf" or t_raw.ndim != 2 or 1 not in t_raw.shape:
        raise SessionError(src, "t", f"shape {t_raw.shape} dtype {t_raw.dtype}", "a numeric N×1 vector, s")
    t = t_raw.astype(float).reshape(-1)
    present = [k for k in SEGMENTS if k in m]
    wanted = present if sensors is None else list(sensors)
    unknown = [k for k in wanted if k not in SEGMENTS]
    if unknown:
        raise SessionError(src, "sensors", f"unknown {unknown}", f"names from {list(SEGMENTS)}")
    missing = [k for k in wanted if k not in m]
    if missing or not wanted:
        raise SessionError(src, missing[0] if missing else "sensors", "missing" if missing else "no sensor struct",
                           f"a struct per sensor ({', '.join(SEGMENTS)}) with fields acc, gyr, quat")
    if "hip" not in wanted:
        raise SessionError(src, "hip", "not read", "the hip (pelvis) sensor: the body model's root")
    dt = float(np.median(np.diff(t))) if t.size > 1 else float("nan")
    out, per = {}, {}
    for name in wanted:
        f = _struct_fields(src, name, m[name])
        for key in ("acc", "gyr"):
            if key not in f:
                raise SessionError(src, f"{name}.{key}", "missing", f"a field {key} (N×3) in struct {name}")
        acc = _array(src, f"{name}.acc", f["acc"], t.size, 3)
        gyr = _array(src, f"{name}.gyr", f["gyr"], t.size, 3)
        seg = segments[name]
        meta = {"format": "qmt-body-mat", "struct": name, "converted": [], "mag_unit": "none (no magnetometer)"}
        quat = None
        if "quat" in f:
            q_file = _array(src, f"{name}.quat", f["quat"], t.size, 4)
            ok = np.all(np.isfinite(q_file), axis=1)
            C, res, used = fit_quat_frame(np.where(ok[:, None], q_file, [1.0, 0, 0, 0]), gyr, dt)
            meta["quat_fit"] = {"bRs": C.tolist(), "median_residual_rad_s": res, "samples": used,
                                "angle_deg": float(np.degrees(np.arccos(np.clip((np.trace(C) - 1) / 2, -1, 1))))}
            if res <= QUAT_FIT_MAX_RAD_S:
                quat = quat_mul(quat_normalize(np.where(ok[:, None], q_file, 1.0)), rotmat_to_quat(C))   # (Q2)
                quat[~ok] = np.nan
                meta["quat_source"] = QUAT_SOURCE
            else:
                meta["quat_note"] = f"file quat not used: (Q1) residual {res:.3f} rad/s > {QUAT_FIT_MAX_RAD_S}"
        mag = np.full((t.size, 3), np.nan)
        s = Session(t, gyr, acc, mag, quat, None, f"{src}:{name}", seg, meta)
        out[seg] = validate_session(s, skip=("mag",))                 # no magnetometer in this recording
        per[seg] = {"struct": name, **{k: v for k, v in meta.items() if k in ("quat_fit", "quat_note")}}
    skel = qmt_skeleton(out, height_m)
    meta = {"format": "qmt-body-mat", "rate_hz": 1.0 / dt, "t_start_s": float(t[0]), "sensors": per,
            "lower_back": lower_back, "magnetometer": False,
            "skeleton": f"full_body({height_m:g} m), Winter's proportions (subject's height not in the file)"}
    return BodySession(t=t, sensors=out, skeleton=skel, truth=None, source=src, name=p.stem, meta=meta)
