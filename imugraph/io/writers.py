"""Results out, written atomically: a temporary file in the target's directory, then os.replace.

A reader of the target path sees either the old file or the complete new one, never a partial
write; on any error the temporary file is removed and the target is untouched.

`calibration.json` (DESIGN.md): ``D`` 3×3 rows, ``o`` (3), ``dip_deg``, ``gyro_bias`` (3, rad/s),
``noise``, ``std``, ``coverage``, ``converged``, ``iterations``, and additive fields (``disturbances``: each
window's ``t_start``/``t_end``, ``offset``, ``modelled`` and ``left_out`` runs [[t_a, t_b], ...] of rows the solve
left out, applied by Calibration.corrected; ``gyro_map``, ...). Non-finite numbers are written as
``null`` (strict JSON) and read back as NaN.
`orientation.npz`: ``t`` (N, s) and ``quat`` (N, 4, w,x,y,z, sensor→nav).
"""

from __future__ import annotations

import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Union

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError

PathLike = Union[str, Path]


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# read once at import: os.umask can only be read by setting it, which races with other threads creating files
_UMASK = _read_umask()


def atomic_write_bytes(path: PathLike, data: bytes) -> Path:
    """Write `data` to `path` through a temporary file in the same directory and os.replace.

    Args:
        path: target file; its directory is created if missing.
        data: the bytes.
    Returns:
        The target path.
    Raises:
        OSError: the directory is not writable (the target is left as it was).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)          # mkstemp makes 0600; a result file gets the usual mode
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return target


def atomic_write_text(path: PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write text atomically (see `atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode(encoding))


def json_ready(obj):
    """JSON-ready copy: numpy → Python, non-finite floats → None (strict JSON), recursively."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def write_calibration_json(path: PathLike, cal: Calibration) -> Path:
    """Write `cal.to_dict()` as indented strict JSON, atomically.

    Args:
        path: target, usually ``<out>/calibration.json``.
        cal: the Calibration.
    Returns:
        The target path.
    """
    text = json.dumps(json_ready(cal.to_dict()), indent=2, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def write_orientation_npz(path: PathLike, t: np.ndarray, quat: np.ndarray) -> Path:
    """Write ``orientation.npz`` with keys ``t`` (N,) s and ``quat`` (N, 4) w,x,y,z sensor→nav.

    Args:
        path: target file.
        t: (N,) s.  quat: (N, 4).
    Returns:
        The target path.
    Raises:
        ValueError: shapes that do not match the contract (a programming error, not bad input).
    """
    t = np.asarray(t, float).reshape(-1)
    quat = np.asarray(quat, float)
    if quat.ndim != 2 or quat.shape != (t.size, 4):
        raise ValueError(f"orientation: quat shape {quat.shape}, expected ({t.size}, 4) for {t.size} times")
    buf = io.BytesIO()
    np.savez(buf, t=t, quat=quat)
    return atomic_write_bytes(path, buf.getvalue())


def _nan(x):
    """Inverse of `json_ready` for numbers: None → NaN, recursively in lists."""
    if x is None:
        return float("nan")
    if isinstance(x, list):
        return [_nan(v) for v in x]
    return x


def _field(src: str, d: dict, key: str, shape: tuple) -> np.ndarray:
    if key not in d:
        raise SessionError(src, key, "missing", f"a {'×'.join(map(str, shape))} array of numbers")
    try:
        arr = np.asarray(_nan(d[key]), dtype=float)
    except (TypeError, ValueError):
        raise SessionError(src, key, f"{str(d[key])[:60]!r}", "numbers") from None
    if arr.shape != shape:
        raise SessionError(src, key, f"shape {arr.shape}", f"shape {shape}")
    return arr


def read_calibration_json(path: PathLike) -> Calibration:
    """Read a calibration.json written by `write_calibration_json`.

    Args:
        path: the file.
    Returns:
        Calibration.
    Raises:
        SessionError: missing file, invalid JSON, missing or malformed D/o/dip_deg, singular D, a malformed
            disturbance window (field 'disturbances[i].t_end' etc.: Calibration.corrected would fail on it).
    """
    src = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SessionError(src, "file", "no such file", "a calibration.json written by imugraph") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(src, "file", f"unreadable ({exc})", "a UTF-8 JSON file") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionError(src, "file", f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}",
                           "a JSON object") from None
    if not isinstance(d, dict):
        raise SessionError(src, "file", f"a JSON {type(d).__name__}", "a JSON object with D, o, dip_deg")
    D = _field(src, d, "D", (3, 3))
    o = _field(src, d, "o", (3,))
    dip = _field(src, d, "dip_deg", ())
    if not np.all(np.isfinite(D)) or abs(np.linalg.det(D)) < 1e-12 * max(1.0, np.abs(D).max() ** 3):
        raise SessionError(src, "D", "a singular or non-finite matrix", "an invertible 3×3 matrix")
    clean = {**d, "D": D.tolist(), "o": o.tolist(), "dip_deg": float(dip)}
    for key in ("gyro_bias",):
        if key in d:
            clean[key] = _field(src, d, key, (3,)).tolist()
    for group in ("noise", "std"):
        if group in d and not isinstance(d[group], dict):
            raise SessionError(src, group, f"a JSON {type(d[group]).__name__}", "an object of arrays")
        clean[group] = {k: _nan(v) for k, v in d.get(group, {}).items()}
    try:
        return Calibration.from_dict(clean)
    except (TypeError, ValueError, KeyError) as exc:
        raise _contract_error(src, str(exc)) from None


def _contract_error(src: str, message: str) -> SessionError:
    """SessionError from a Calibration.from_dict ValueError: "FIELD: FOUND, expected EXPECTED" names the field
    (e.g. disturbances[0].t_end); any other message is reported against the whole file."""
    field, sep, rest = message.partition(": ")
    found, sep2, expected = rest.rpartition(", expected ")
    if sep and sep2 and field and " " not in field:
        return SessionError(src, field, found, expected)
    return SessionError(src, "file", f"malformed calibration ({message})", "the calibration.json contract")
