"""`load_session`: one entry point for every session format, then validation.

Dispatch (extension first, then the file's first bytes when the extension is unknown or lies):

| input | reader |
|---|---|
| folder with Inertial.csv + Magnetometer.csv | x-IMU3 (`xio.read_ximu3_folder`) |
| `.npz` (zip archive) | NPZ contract below |
| `.mat` MATLAB v5 | BROAD (``imu_gyr``…) or Rasteiro (``SENSgyro``…) by the variables inside |
| `.hdf5`, `.h5`, `.mat` v7.3 (HDF5) | BROAD HDF5 |
| `.csv` | imugraph columns, or an x-io export recognised by its header |
| `.txt` | Xsens MTw export (``//`` header lines), else CSV |

NPZ contract: ``gyr`` (N, 3) rad/s, ``acc`` (N, 3) m/s², ``mag`` (N, 3) any unit (NaN rows = no
sample), and ``rate`` (Hz, scalar; ``sampling_rate``, BROAD's name, is read as an alias) or ``t`` (N,) s
increasing; optional ``quat`` (N, 4) w,x,y,z nRb truth, ``movement`` (N,) bool, and ``gaps`` (M, 2) s: pairs
``[t_before, t_after]`` of the declared gaps in ``t`` (samples that never arrived: a gap longer than 5 median steps
is refused unless declared here or by ``load_session(..., allow_gaps=True)`` / ``--allow-gaps``; the gap model,
factors/gaps.py, then applies); other keys are ignored (listed in ``meta["ignored_keys"]``).

imugraph CSV: one header line, comma-separated, columns ``t`` (or ``time_s``) in s,
``gyr_x, gyr_y, gyr_z`` rad/s, ``acc_x, acc_y, acc_z`` m/s², ``mag_x, mag_y, mag_z`` (empty cells
or ``nan`` where no sample), optional ``quat_w, quat_x, quat_y, quat_z`` and ``movement`` (0/1).
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Union

import numpy as np

from imugraph.errors import SessionError
from imugraph.io.broad import MAT_ERRORS, read_broad_hdf5, read_broad_mat_fields
from imugraph.io.rasteiro import VARIABLES as RASTEIRO_VARS, read_rasteiro_fields
from imugraph.io.session import Session
from imugraph.io.validate import GAP_STEPS, NO_MAG, as_array, validate_session
from imugraph.io.xio import is_xio_header, read_csv_table, read_fusion_csv, read_ximu3_folder
from imugraph.io.xsens import read_xsens_mtw

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
ZIP_MAGIC = b"PK\x03\x04"
MAT5_MAGIC = b"MATLAB 5.0 MAT-file"
NPZ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)
NPZ_KEYS = ("gyr", "acc", "mag", "rate", "sampling_rate", "t", "quat", "movement", "gaps")
BROAD_VARS = ("imu_gyr", "imu_acc", "imu_mag", "sampling_rate", "opt_quat", "movement")


def read_npz(path: Path, *, mag_optional: bool = False) -> Session:
    """Session from an NPZ following the contract in the module docstring.

    Args:
        path: the .npz file.
        mag_optional: a file without 'mag' (a 6-axis IMU) reads with mag all NaN instead of failing (body-session
            sensors: mocap runs without magnetometers by default); False (default): 'mag' is required.
    Returns:
        Session, not yet validated.
    Raises:
        SessionError: not a zip/npz archive, truncated member, missing or malformed key.
    """
    src = str(path)
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise SessionError(src, "file", "a single .npy array", "an .npz archive (numpy.savez)")
        with z:
            keys = list(z.keys())
            arrays = {k: z[k] for k in NPZ_KEYS if k in keys}
    except NPZ_ERRORS as exc:
        raise SessionError(src, "file", f"not a readable .npz archive ({type(exc).__name__}: {exc})",
                           "an .npz archive written by numpy.savez") from None
    for k in ("gyr", "acc", "mag"):
        if k not in arrays and not (k == "mag" and mag_optional):
            raise SessionError(src, k, f"missing (keys: {', '.join(keys) or 'none'})",
                               "an (N, 3) array" + (f"; {NO_MAG}" if k == "mag" else ""))
    gyr = as_array(src, "gyr", arrays["gyr"], 3)
    n = gyr.shape[0]
    acc = as_array(src, "acc", arrays["acc"], 3, n)
    mag = as_array(src, "mag", arrays["mag"], 3, n) if "mag" in arrays else np.full((n, 3), np.nan)
    t = _npz_time(src, arrays, n)
    quat = as_array(src, "quat", arrays["quat"], 4, n) if "quat" in arrays else None
    movement = as_array(src, "movement", arrays["movement"], None, n).astype(bool) if "movement" in arrays else None
    ignored = sorted(set(keys) - set(NPZ_KEYS))
    meta = {"format": "npz", "converted": [], "ignored_keys": ignored}
    if "rate" not in arrays and "sampling_rate" in arrays and "t" not in arrays:
        meta["converted"].append("'sampling_rate' read as 'rate'")
    if "gaps" in arrays:
        meta["gaps"] = _npz_gaps(src, arrays["gaps"])
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=quat, movement=movement, source=src,
                   name=path.stem, meta=meta)


def _npz_time(src: str, arrays: dict, n: int) -> np.ndarray:
    if "t" in arrays:
        return as_array(src, "t", arrays["t"], None, n)
    key = "rate" if "rate" in arrays else "sampling_rate"       # BROAD's name, an alias (U22 defect 12)
    if key not in arrays:
        raise SessionError(src, "rate", "neither 'rate' (nor its alias 'sampling_rate') nor 't'",
                           "'rate' (Hz, scalar) or 't' (N,) in s")
    rate = np.asarray(arrays[key])
    ok = rate.dtype.kind in "biuf" and rate.size == 1 and bool(np.isfinite(rate).all())
    if not ok or float(rate.reshape(-1)[0]) <= 0:
        raise SessionError(src, key, f"{rate!r:.60}", "one positive number in Hz")
    return np.arange(n) / float(rate.reshape(-1)[0])


def _npz_gaps(src: str, gaps) -> list:
    """The NPZ's declared gaps: (M, 2) finite [t_before, t_after] pairs in s, t_before < t_after → meta["gaps"]."""
    g = np.asarray(gaps)
    if g.size == 0:
        return []
    ok = g.dtype.kind in "biuf" and g.ndim == 2 and g.shape[1] == 2 and bool(np.isfinite(g).all())
    if not ok or not np.all(g[:, 0] < g[:, 1]):
        found = f"shape {g.shape}, dtype {g.dtype}" if not ok else "a pair with t_before ≥ t_after"
        raise SessionError(src, "gaps", found, "(M, 2) pairs [t_before, t_after] in s, t_before < t_after")
    return [[float(a), float(b)] for a, b in g]


def _cols(spec: dict, names: tuple) -> list:
    return [spec[c] for c in names]


def read_imugraph_csv(path: Path, cols: list, data: np.ndarray) -> Session:
    """Session from an imugraph CSV (columns in the module docstring).

    Args:
        path: the file.  cols, data: the parsed table.
    Returns:
        Session, not yet validated.
    Raises:
        SessionError: a missing column.
    """
    src = str(path)
    spec = {c.strip().lower(): i for i, c in enumerate(cols)}
    tcol = next((c for c in ("t", "time_s") if c in spec), None)
    if tcol is None:
        raise SessionError(src, "t", f"no time column (columns: {', '.join(cols)})", "a column 't' or 'time_s' in s")
    blocks = {}
    for q in ("gyr", "acc", "mag"):
        names = tuple(f"{q}_{a}" for a in "xyz")
        missing = [c for c in names if c not in spec]
        if missing:
            six = q == "mag" and len(missing) == 3                      # no mag_* column: a 6-axis recording
            raise SessionError(src, missing[0], "column missing" + (" (no magnetometer: a 6-axis recording)" if six
                               else ""), f"columns {', '.join(names)}" + (f"; {NO_MAG}" if six else ""))
        blocks[q] = data[:, _cols(spec, names)]
    quat_names = tuple(f"quat_{a}" for a in "wxyz")
    quat = data[:, _cols(spec, quat_names)] if all(c in spec for c in quat_names) else None
    movement = data[:, spec["movement"]] > 0.5 if "movement" in spec else None
    return Session(t=data[:, spec[tcol]], gyr=blocks["gyr"], acc=blocks["acc"], mag=blocks["mag"], quat=quat,
                   movement=movement, source=src, name=path.stem, meta={"format": "csv", "converted": []})


def read_csv(path: Path) -> Session:
    """imugraph CSV or x-io CSV, told apart by the header."""
    cols, data = read_csv_table(path)
    if is_xio_header(cols):
        return read_fusion_csv(path, cols, data)
    return read_imugraph_csv(path, cols, data)


def read_mat(path: Path) -> Session:
    """MATLAB v5 .mat: BROAD or Rasteiro, by the variables it holds."""
    import warnings

    import scipy.io

    src = str(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # Rasteiro files repeat a variable named "None"
            fields = scipy.io.loadmat(path, variable_names=list(BROAD_VARS + RASTEIRO_VARS))
    except MAT_ERRORS as exc:
        raise SessionError(src, "file", f"an unreadable MATLAB file ({type(exc).__name__}: {exc})",
                           "a MATLAB v5 .mat with BROAD or Rasteiro variables") from None
    if "imu_gyr" in fields:
        return read_broad_mat_fields(path, fields)
    if "SENSgyro" in fields or "ABBquaternion" in fields:    # Rasteiro (XSENS.mat has no SENSgyro: refused there)
        return read_rasteiro_fields(path, fields)
    names = _mat_names(path, fields)
    body = " (one struct per sensor: a body recording is read by `imugraph mocap`)" if names.count("(struct)") > 1 else ""
    raise SessionError(src, "imu_gyr", f"neither BROAD nor Rasteiro variables (found: {names})",
                       "BROAD imu_gyr/imu_acc/imu_mag/sampling_rate or Rasteiro SENSgyro/SENSacc/SENSmag" + body)


def _mat_names(path: Path, fields: dict, most: int = 8) -> str:
    """The file's variables for the refusal: loadmat read only the known names, so list them with whosmat (the
    QMT full-body file said "found: none" though it holds t, foot_left, … — U22 defect 15)."""
    import scipy.io

    try:
        names = [f"{n} ({kind})" if kind == "struct" else n for n, _, kind in scipy.io.whosmat(path)]
    except MAT_ERRORS:
        names = [k for k in fields if not k.startswith("__")]
    if not names:
        return "no variables"
    more = f", … ({len(names)} in all)" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def _sniff(path: Path) -> str:
    """Format from the first bytes: 'npz', 'hdf5', 'mat', 'text' or 'unknown'."""
    with open(path, "rb") as fh:
        head = fh.read(1024)
    if head.startswith(ZIP_MAGIC):
        return "npz"
    if head.startswith(HDF5_MAGIC) or head[512:520] == HDF5_MAGIC:
        return "hdf5"
    if head.startswith(MAT5_MAGIC):
        return "mat"
    if b"\x00" not in head[:128] and head:
        return "text"
    return "unknown"


def _read_any(path: Path) -> Session:
    src = str(path)
    if path.is_dir():
        if (path / "Inertial.csv").is_file():
            return read_ximu3_folder(path)
        from imugraph.io.xio_body import sensor_folders

        sensors = [p.name for p in sensor_folders(path)]
        if sensors or (path / "session.json").is_file():    # several IMUs: `imugraph mocap` reads it (U22 #15)
            found = (f"a body session folder ({len(sensors)} x-IMU3 sensor folders: {', '.join(sensors[:3])}"
                     f"{', …' if len(sensors) > 3 else ''})" if sensors else "a body session folder (session.json)")
            raise SessionError(src, "Inertial.csv", found, "one IMU: an x-IMU3 export folder or a session file "
                               "(a body session is read by `imugraph mocap`)")
        raise SessionError(src, "Inertial.csv", "a folder without Inertial.csv", "an x-IMU3 export folder or a file")
    if not path.is_file():
        raise SessionError(src, "file", "no such file", "an existing session file or folder")
    if path.stat().st_size == 0:
        raise SessionError(src, "file", "an empty file (0 bytes)", "a session file (.npz, .mat, .hdf5, .csv, .txt)")
    kind, ext = _sniff(path), path.suffix.lower()
    if ext == ".npz" or (kind == "npz" and ext not in (".mat", ".hdf5", ".h5")):
        if kind != "npz":
            raise SessionError(src, "file", f"{'text' if kind == 'text' else 'bytes'}, not a zip archive",
                               "an .npz archive written by numpy.savez")
        return read_npz(path)
    if kind == "hdf5" or ext in (".hdf5", ".h5"):
        if kind != "hdf5":
            raise SessionError(src, "file", "no HDF5 signature", "an HDF5 file (BROAD .hdf5)")
        return read_broad_hdf5(path)
    if ext == ".mat" or kind == "mat":
        return read_mat(path)
    if ext == ".csv":
        return read_csv(path)
    if kind == "text" and _is_xsens(path):
        return read_xsens_mtw(path)
    if ext == ".txt":
        return read_csv(path)
    raise SessionError(src, "file", f"unknown format (extension '{ext}')",
                       ".npz, .mat, .hdf5/.h5, .csv, .txt (Xsens) or an x-IMU3 folder")


def _is_xsens(path: Path) -> bool:
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        first = fh.readline()
    return first.startswith("//") or first.startswith("PacketCounter")


def declare_gaps(s: Session) -> Session:
    """The session with every step longer than `GAP_STEPS` median steps declared in ``meta["gaps"]`` (the user's
    --allow-gaps: samples that never arrived, not a broken time base); the gap model (factors/gaps.py) then treats
    the missing time. A copy with a new meta when a gap was added; the same Session otherwise (input not modified).
    Non-finite or unsorted times are left for `validate_session` to report."""
    t = np.asarray(s.t, float)
    if t.ndim != 1 or t.size < 3 or not np.all(np.isfinite(t)):
        return s
    dt = np.diff(t)
    if np.any(dt <= 0):
        return s
    med = float(np.median(dt))
    idx = np.flatnonzero(dt > GAP_STEPS * med)
    if idx.size == 0:
        return s
    meta = dict(s.meta) if isinstance(s.meta, dict) else {}
    meta["gaps"] = list(meta.get("gaps", [])) + [[float(t[i]), float(t[i + 1])] for i in idx]
    meta["gaps_declared_by"] = "allow_gaps"
    return replace(s, meta=meta)

def load_session(path: Union[str, Path], *, validate: bool = True, allow_gaps: bool = False) -> Session:
    """Read a session from any supported format and (by default) validate it.

    Args:
        path: file or x-IMU3 folder.
        validate: run `validate_session` (repairs isolated NaN samples, rejects bad input).
        allow_gaps: declare every gap of more than 5 median steps in ``meta["gaps"]`` (samples that never
            arrived; `declare_gaps`) instead of refusing it; the CLI's --allow-gaps.
    Returns:
        Session: t (N,) s, gyr (N, 3) rad/s, acc (N, 3) m/s², mag (N, 3) in the file's unit with NaN
        rows where no sample, optional quat (N, 4) and movement (N,); conversions in meta["converted"].
    Raises:
        SessionError: unreadable or invalid input; the message names the file and the field.
    """
    try:
        session = _read_any(Path(path))
    except OSError as exc:                    # permissions, I/O errors: still one clear line
        raise SessionError(str(path), "file", f"unreadable ({exc.strerror or exc})", "a readable file") from None
    if allow_gaps:
        session = declare_gaps(session)
    return validate_session(session) if validate else session
