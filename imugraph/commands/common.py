"""Helpers shared by the subcommands: session paths, output folders, progress, scores, output files.

Progress lines go to stderr (silenced by --quiet); result tables go to stdout.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Optional

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.errors import ImugraphError, SessionError
from imugraph.io.session import Session

if TYPE_CHECKING:
    from imugraph.calibration.ml import Estimate

DEFAULT_OUT_ROOT = Path("imugraph_out")


@dataclass
class Progress:
    """Short progress lines on stderr, each with the time elapsed since the command started.

    Attributes:
        quiet: print nothing.
        start: `time.perf_counter()` at creation, s.
    """

    quiet: bool = False
    start: float = field(default_factory=time.perf_counter)

    def say(self, message: str) -> None:
        """Print one progress line to stderr unless quiet."""
        if not self.quiet:
            print(f"[{time.perf_counter() - self.start:6.1f} s] {message}", file=sys.stderr, flush=True)

    @contextlib.contextmanager
    def library_output(self) -> Iterator[None]:
        """Send what library code prints (e.g. the ML loop's per-round lines) to stderr, not stdout."""
        with contextlib.redirect_stdout(sys.stderr):
            yield


def resolve_session_path(session: str, data_dir: Optional[str], strict: bool = True) -> Path:
    """The session file: `session` as given, else relative to the data directory, else a unique match in the data
    directory's subfolders (`imugraph.config.find_session`).

    Args:
        session: path of a session file or x-IMU3 folder, absolute or relative.
        data_dir: --data-dir value, or None for `imugraph.config.data_dir()`.
        strict: raise when nothing (or more than one file) matches; False returns `session` unchanged so that
            the reader names it (batch: one missing session must not stop the others).

    Returns:
        The existing path (or `session` unchanged, strict=False).

    Raises:
        SessionError: field 'file': not found, naming the places looked in, or several matches (strict only).
    """
    from imugraph.config import find_session

    try:
        return find_session(session, data_dir)
    except SessionError:
        if strict:
            raise
        return Path(session).expanduser()


def load_with_calibration(args, progress: Progress) -> tuple[Path, Session, Optional[Calibration]]:
    """smooth's and stream's start: --calibration FILE read first (a bad file fails before any long work), the
    session resolved and loaded, then the calibration refused if it belongs to another sensor (median
    |D⁻¹(y − o)| far from 1, `imugraph.io.validate.check_calibration_applies`).

    Returns:
        (session path, session, Calibration or None without --calibration).
    """
    cal = None
    if args.calibration:
        from imugraph.io.writers import read_calibration_json
        cal = read_calibration_json(Path(args.calibration).expanduser())
        cal = _dip_in_convention(cal, args.calibration, progress)
    path = resolve_session_path(args.session, args.data_dir)
    session = load(path, progress, getattr(args, "allow_gaps", False))
    check_keyframe_hz(session, getattr(args, "keyframe_hz", None))
    if cal is not None:
        from imugraph.io.validate import check_calibration_applies
        check_calibration_applies(session, cal, args.calibration)
    return path, session, cal


# --keyframe-hz upper bound: 10× calibrate's default 5 Hz, 5× the stream's 10 Hz. The ML loop's cost grows faster than
# the keyframe count: the first 60 s of BROAD 06 (285.7 Hz) 1.0 s CPU at 5 Hz, 4.0 s at 20, 7.4 s at 50, > 120 s at
# 1000 (= every sample, U22 defect 9: killed, an empty --out left behind).
MAX_KEYFRAME_HZ = 50.0


def check_keyframe_hz(session: Session, keyframe_hz: Optional[float]) -> None:
    """Refuse a --keyframe-hz above the session's sample rate (a keyframe per sample at most: the rest is a runaway
    solve, not more accuracy) or above MAX_KEYFRAME_HZ, before any output folder is made.

    Raises:
        SessionError: field 'keyframe_hz', naming the sample rate and the bound.
    """
    if keyframe_hz is None:
        return
    limit = min(session.rate, MAX_KEYFRAME_HZ)
    if keyframe_hz > limit:
        raise SessionError(session.source, "keyframe_hz", f"--keyframe-hz {keyframe_hz:g} (sample rate "
                           f"{session.rate:.1f} Hz)", f"at most {limit:.4g} Hz (≤ the sample rate and ≤ "
                           f"{MAX_KEYFRAME_HZ:g} Hz; default 5 for calibrate/smooth, 10 for stream)")


def _dip_in_convention(cal: Calibration, source: str, progress: Progress) -> Calibration:
    """A calibration.json with |dip| > 90° (written before calibrate folded it, or edited) folded to DESIGN's
    convention (calibration.dip_fold: δ' = ±180° − δ, the same model with the nav frame turned by 180° about the
    vertical), said on the progress stream: smoothing it unfolded gave 48.29° instead of 0.57° (U22 defect 1)."""
    from imugraph.calibration.dip_fold import folded_calibration

    folded = folded_calibration(cal)
    if folded is not cal:
        progress.say(f"{source}: dip {cal.dip_deg:.3f}° folded to {folded.dip_deg:.3f}° (|dip| ≤ 90°, x along the "
                     "horizontal field: the nav frame turned by 180° about the vertical)")
    return folded


def out_dir_for(out: Optional[str], stem: str) -> Path:
    """Output folder: --out when given, else imugraph_out/<stem>; created (with parents) if missing and checked
    writable at once, so that a read-only --out fails before any long computation (not at the first write).

    Raises:
        SessionError: the folder cannot be created or written (field 'out').
    """
    path, _ = _make_out_dir(out, stem)
    return path


def _make_out_dir(out: Optional[str], stem: str) -> tuple[Path, list[Path]]:
    """`out_dir_for`, also returning the folders it created (deepest first) so that a failed run can remove them."""
    path = Path(out).expanduser() if out else DEFAULT_OUT_ROOT / stem
    created = [p for p in (path, *path.parents) if not p.exists()]
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SessionError(str(path), "out", f"a folder that cannot be created ({exc.strerror})",
                           "a writable output folder (--out DIR)") from None
    try:                                   # a real write: os.access says yes to root on a read-only folder
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        _remove_empty(created)
        raise SessionError(str(path), "out", f"a folder that cannot be written ({exc.strerror or exc})",
                           "a writable output folder (--out DIR)") from None
    return path, created


def _remove_empty(folders: list[Path]) -> None:
    """rmdir each folder (deepest first) that is empty; a folder holding anything stays."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


@contextlib.contextmanager
def output_folder(out: Optional[str], stem: str) -> Iterator[Path]:
    """`out_dir_for` for the length of a command: the folder it created is removed again when the command
    fails (any exception, Ctrl-C included) and nothing was written into it — no empty --out left behind.

    Raises:
        SessionError: the folder cannot be created or written (field 'out').
    """
    path, created = _make_out_dir(out, stem)
    try:
        yield path
    except BaseException:
        _remove_empty(created)
        raise


def load(path: Path, progress: Progress, allow_gaps: bool = False) -> Session:
    """Load and validate a session, announcing it on the progress stream; allow_gaps: --allow-gaps (gaps of more
    than 5 median steps declared as missing samples, `imugraph.io.readers.load_session`).

    Raises:
        SessionError: unreadable or invalid input.
    """
    from imugraph.io.readers import load_session

    progress.say(f"reading {path}")
    session = load_session(path, allow_gaps=allow_gaps)
    gaps = session.meta.get("gaps") if isinstance(session.meta, dict) else None
    if gaps and session.meta.get("gaps_declared_by") == "allow_gaps":
        progress.say(f"--allow-gaps: {len(gaps)} gap(s) declared, {sum(b - a for a, b in gaps):.3g} s without samples")
    progress.say(f"{session.n} samples, {session.t[-1] - session.t[0]:.1f} s at {session.rate:.1f} Hz, "
                 f"{int(session.mag_valid.sum())} magnetometer samples")
    return session


@dataclass(frozen=True)
class Scores:
    """How good a calibration and an orientation are.

    Attributes:
        norm_before: RMS of |b_mag|/median|b_mag| − 1 on the raw field (dimensionless).
        norm_after: RMS of |D⁻¹(b_mag − o)| − 1 (dimensionless; disturbance windows applied, field_norm_scores).
        orientation_rms_deg: RMS orientation error against the session's truth quat (best heading
            offset and time shift removed), degrees; None without truth.
        reference: what the session's quat is (`reference_label`): "truth", or "reference [<source>]" for a
            device's own orientation estimate (meta["quat_source"], e.g. an onboard AHRS).

    A norm is NaN when it cannot be computed (no finite calibrated sample, e.g. a magnetometer that reads 0).
    """

    norm_before: float
    norm_after: float
    orientation_rms_deg: Optional[float]
    reference: str = "truth"


def reference_label(session: Session) -> str:
    """"truth", or "reference [<meta quat_source>]" when the session's quat is a device's own estimate."""
    source = (session.meta or {}).get("quat_source") if isinstance(session.meta, dict) else None
    return f"reference [{source}]" if source else "truth"


def field_norm_scores(session: Session, cal: Calibration) -> tuple[float, float]:
    """Field-norm RMS error of the raw field scaled by its median norm, and of the calibrated field.

    Args:
        session: the recording (mag (N, 3), NaN rows where no sample).
        cal: Calibration with apply(b_mag) = D⁻¹(b_mag − o); with disturbance windows the calibrated field is
            that of the model (`Calibration.corrected`: a modelled window's offset removed, an unexplained
            window's samples not scored) — a stream's calibration.json whose windows hold the majority of the
            recording (StreamOptions.calib_json_end_graph) scored 98 % without them (docs/stream.md, helper M1).

    Returns:
        (before, after), dimensionless RMS of |field| − 1.
    """
    from imugraph.evaluate import field_norm_error

    valid = session.mag_valid
    norms = np.linalg.norm(session.mag[valid], axis=1)
    raw_scale = float(np.median(norms)) if norms.size else 0.0
    with np.errstate(divide="ignore", invalid="ignore"):       # a dead (all-zero) field: NaN, not a warning
        raw = session.mag / raw_scale if raw_scale > 0 else np.full_like(session.mag, np.nan)
        calibrated = cal.calibrated_field(session.t, session.mag)
    # "after" over the calibrated field's own finite rows: with a magnetometer lag they are the raw rows shifted by
    # round(τ/Δt) (Calibration.corrected), which on a lower-rate field never meet the unshifted `valid` rows (a field
    # every 4th row, lag 2–3 rows: "after n/a", U22 defect 4); with a field on every row this is the same set
    with_sample = np.all(np.isfinite(calibrated), axis=1)
    return (_norm_error_or_nan(field_norm_error, raw, valid),
            _norm_error_or_nan(field_norm_error, calibrated, with_sample))


def _norm_error_or_nan(field_norm_error, b_mag: np.ndarray, valid: np.ndarray) -> float:
    """field_norm_error, NaN when no row is finite (the score is then printed as n/a, the outputs kept)."""
    if not np.any(np.all(np.isfinite(b_mag), axis=1) & valid):
        return float("nan")
    return field_norm_error(b_mag, valid)


def orientation_score(session: Session, quat: np.ndarray) -> Optional[float]:
    """RMS orientation error in degrees against session.quat (over session.movement), None without truth."""
    if session.quat is None:
        return None
    from imugraph.evaluate import orientation_error

    try:
        return orientation_error(quat, session.quat, session.movement, session.rate).rms_deg
    except ImugraphError:      # truth present but not scorable (all NaN, too short)
        return None


def score(session: Session, cal: Calibration, quat: np.ndarray) -> Scores:
    """Field-norm errors before/after and the orientation error of one result (see `Scores`)."""
    before, after = field_norm_scores(session, cal)
    return Scores(before, after, orientation_score(session, quat), reference_label(session))


def write_orientation(out: Path, t: np.ndarray, quat: np.ndarray, progress: Progress) -> Path:
    """Write orientation.npz (t (N,), quat (N, 4) w,x,y,z nRb) atomically into `out`."""
    from imugraph.io.writers import write_orientation_npz

    path = out / "orientation.npz"
    write_orientation_npz(path, t, quat)
    progress.say(f"wrote {path}")
    return path


def write_calibration(out: Path, cal: Calibration, progress: Progress) -> Path:
    """Write calibration.json atomically into `out`."""
    from imugraph.io.writers import write_calibration_json

    path = out / "calibration.json"
    write_calibration_json(path, cal)
    progress.say(f"wrote {path}")
    return path


def write_estimate(out: Path, session: Session, estimate: "Estimate", progress: Progress) -> list[Path]:
    """Every output of a calibration: calibration.json, orientation.npz, calibration.png, heading.png.

    Args:
        out: existing output folder.
        session: the calibrated recording.
        estimate: `imugraph.calibration.ml.Estimate` (calibration, t, quat (N, 4), residuals).
        progress: progress stream.

    Returns:
        The paths written.
    """
    from imugraph.io.figures import plot_calibration, plot_heading

    cal = estimate.calibration
    paths = [write_calibration(out, cal, progress), write_orientation(out, estimate.t, estimate.quat, progress)]
    progress.say("drawing figures")
    png = out / "calibration.png"
    # the calibrated field of the model, as the console's "after" score (field_norm_scores): with disturbance
    # windows a modelled window's offset removed, an unexplained window's samples left out (Calibration.corrected)
    velocity = (estimate.info or {}).get("velocity") if isinstance(estimate.info, dict) else None
    plot_calibration(png, session.mag, cal.calibrated_field(session.t, session.mag), session.t, estimate.residuals,
                     whitened=True, title=f"Magnetometer calibration: {session.name}",
                     not_in_cost=("acc",) if velocity is not None else ())
    heading = out / "heading.png"
    # aligned (time shift, heading offset) over `movement` as the console's orientation score (orientation_score)
    plot_heading(heading, estimate.t, estimate.quat, session.quat, title=f"Heading: {session.name}",
                 align=True, mask=session.movement, reference_label=reference_label(session))
    paths += [png, heading]
    progress.say(f"wrote {png} and {heading}")
    return paths
