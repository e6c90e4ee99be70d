"""Helpers shared by the subcommands: session paths, output folders, progress, scores, output files.

Progress lines go to stderr (silenced by --quiet); result tables go to stdout.
"""

from __future__ import annotations

import contextlib
import sys
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


def resolve_session_path(session: str, data_dir: Optional[str]) -> Path:
    """The session file: `session` as given, else relative to the data directory.

    Args:
        session: path of a session file or x-IMU3 folder, absolute or relative.
        data_dir: --data-dir value, or None for `imugraph.config.data_dir()`.

    Returns:
        The existing path, or `session` unchanged when neither exists (the reader then names it).
    """
    path = Path(session).expanduser()
    if path.exists() or path.is_absolute():
        return path
    from imugraph.config import data_dir as default_data_dir

    base = Path(data_dir).expanduser() if data_dir else default_data_dir()
    candidate = base / path
    return candidate if candidate.exists() else path


def out_dir_for(out: Optional[str], stem: str) -> Path:
    """Output folder: --out when given, else imugraph_out/<stem>; created (with parents) if missing.

    Raises:
        SessionError: the folder cannot be created (field 'out').
    """
    path = Path(out).expanduser() if out else DEFAULT_OUT_ROOT / stem
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SessionError(str(path), "out", f"a folder that cannot be created ({exc.strerror})",
                           "a writable output folder (--out DIR)") from None
    return path


def load(path: Path, progress: Progress) -> Session:
    """Load and validate a session, announcing it on the progress stream.

    Raises:
        SessionError: unreadable or invalid input.
    """
    from imugraph.io.readers import load_session

    progress.say(f"reading {path}")
    session = load_session(path)
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
    """

    norm_before: float
    norm_after: float
    orientation_rms_deg: Optional[float]


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
    raw_scale = float(np.median(np.linalg.norm(session.mag[valid], axis=1)))
    y = cal.corrected(session.t, session.mag) if cal.disturbances else session.mag
    return (field_norm_error(session.mag / raw_scale, valid), field_norm_error(cal.apply(y), valid))


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
    return Scores(before, after, orientation_score(session, quat))


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
    plot_calibration(png, session.mag, cal.apply(session.mag), session.t, estimate.residuals, whitened=True,
                     title=f"Magnetometer calibration: {session.name}")
    heading = out / "heading.png"
    plot_heading(heading, estimate.t, estimate.quat, session.quat, title=f"Heading: {session.name}")
    paths += [png, heading]
    progress.say(f"wrote {png} and {heading}")
    return paths
