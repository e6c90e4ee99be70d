"""`imugraph diagnose SESSION --out DIR`: where the sim-to-real gap lies, which unmodelled effect explains
it and how far it shrinks (imugraph.diagnose.run.diagnose); writes diagnosis.json, diagnosis.md,
gap_over_time.png and residuals.png, and prints a short summary.

SESSION: a single-IMU session file (.npz, .mat, .hdf5, .csv, .txt) or x-IMU3 folder, or a body session (any
SESSION of `imugraph mocap`: a folder with session.json, a gaittoolbox rawimu folder, a folder of x-IMU3 export
folders, an .mvnx file, the qmt full-body .mat; `_is_body_session`), diagnosed by imugraph.diagnose.body. A body
session's base model takes its placements and noise from the N-pose window, found as in `imugraph mocap` (the
common rest of all sensors at the start) or given with --npose T0,T1; a session with neither is refused with
one line (session 23: it was fitted from its first samples in motion, e.g. the qmt full body).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imugraph.commands import common


def run_diagnose(args: argparse.Namespace) -> int:
    """diagnose SESSION [--out DIR] [--keyframe-hz HZ] [--seed N] [--effects a,b] [--npose T0,T1] [--data-dir DIR]
    [--quiet] (--npose: body sessions only, as mocap's).

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    from imugraph.diagnose.report import summary_table, write_report
    from imugraph.diagnose.run import DiagnoseOptions, diagnose

    progress = common.Progress(getattr(args, "quiet", False))
    path = common.resolve_session_path(args.session, getattr(args, "data_dir", None))
    if _is_body_session(Path(path)):                      # multi-IMU: imugraph.diagnose.body (issue 5, G1)
        return _run_body(args, Path(path), progress)
    if getattr(args, "npose", None):
        from imugraph.errors import SessionError
        raise SessionError("--npose", "SESSION", f"a single-IMU session ({path})", "a body session for --npose")
    session = common.load(path, progress)
    options = DiagnoseOptions(keyframe_hz=float(getattr(args, "keyframe_hz", 5.0) or 5.0),
                              seed=int(getattr(args, "seed", 0) or 0), effects=_effect_names(args))
    # --out created and write-checked before the computation, removed again if a failed run left it empty
    with common.output_folder(getattr(args, "out", None), Path(path).stem) as out:
        with progress.library_output():
            diag = diagnose(session, options, progress=progress.say)
        return _report(diag, out, progress, write_report, summary_table)


def _effect_names(args: argparse.Namespace) -> tuple | None:
    """--effects a,b as a tuple of names (None: the whole library)."""
    names = getattr(args, "effects", None)
    return tuple(n.strip() for n in names.split(",") if n.strip()) if names else None


def _report(diag, out: Path, progress, write_report, summary_table) -> int:
    """Write the report files, say where, print the summary table."""
    paths = write_report(diag, out)
    progress.say(f"wrote {', '.join(sorted(paths))} in {out}")
    print(summary_table(diag))
    return 0


def _is_body_session(path: Path) -> bool:
    """A multi-IMU session (imugraph.io.body_session.read_body_session): own folder with session.json, a
    gaittoolbox Xsens MTw folder, a folder of x-IMU3 export folders, an .mvnx file, or the qmt full-body .mat
    (which `imugraph mocap` reads; session 23: before, diagnose took it for a single-IMU .mat)."""
    from imugraph.io.body_session import is_body_session
    from imugraph.io.qmt_body import is_qmt_body_mat

    return is_body_session(path) or (path.is_file() and path.suffix.lower() == ".mat" and is_qmt_body_mat(path))


def _run_body(args: argparse.Namespace, path: Path, progress) -> int:
    """The body diagnosis (imugraph.diagnose.body.run.diagnose_body) and its report."""
    from imugraph.diagnose.body.report import summary_table, write_report
    from imugraph.diagnose.body.run import BodyDiagnoseOptions, diagnose_body
    from imugraph.io.body_session import read_body_session

    progress.say(f"reading body session {path}")
    session = read_body_session(path)
    progress.say(f"{len(session.sensors)} sensors, {session.n} samples, {session.t[-1] - session.t[0]:.1f} s")
    from imugraph.commands.mocap import npose_window
    from imugraph.graphs.body_model import BodyOptions

    npose = npose_window(getattr(args, "npose", None))          # mocap's --npose (None: detected at the start)
    options = BodyDiagnoseOptions(seed=int(getattr(args, "seed", 0) or 0), effects=_effect_names(args),
                                  body_options=None if npose is None else BodyOptions(npose=npose),
                                  npose_check=True)            # refuse a session without a found N-pose
    with common.output_folder(getattr(args, "out", None), path.stem) as out:     # no empty folder left on failure
        with progress.library_output():
            diag = diagnose_body(session, options, progress=progress.say)
        return _report(diag, out, progress, write_report, summary_table)
