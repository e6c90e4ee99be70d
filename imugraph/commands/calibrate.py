"""`imugraph calibrate` and `imugraph smooth`.

calibrate SESSION: maximum-likelihood magnetometer calibration with the inertial sensors (Kok & Schön,
`imugraph.calibration.ml.calibrate`), writing calibration.json, orientation.npz, calibration.png and
heading.png, and printing the result table.
smooth SESSION: the smoothed orientation only — with a known calibration (--calibration FILE, GTSAM C++
factors, `imugraph.graphs.cpp_smoother.smooth_fixed`), or estimated on the way (then calibration.json too).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from imugraph.commands import common
from imugraph.calibration.result import Calibration
from imugraph.commands.report import calibration_table, score_lines
from imugraph.io.session import Session

if TYPE_CHECKING:
    from imugraph.calibration.ml import Estimate


def estimate_calibration(session: Session, keyframe_hz: float, progress: common.Progress) -> "Estimate":
    """Run the ML calibration (`imugraph.calibration.ml.calibrate`), its per-round lines on stderr.

    Args:
        session: the recording.
        keyframe_hz: orientation states per second.
        progress: progress stream (quiet: the ML loop prints nothing either).

    Returns:
        Estimate: calibration, t (N,), quat (N, 4) nRb w,x,y,z, whitened residuals per channel.

    Raises:
        CalibrationError: the data do not allow a calibration (e.g. too little rotation).
    """
    from imugraph.calibration.ml import Options, calibrate

    progress.say(f"calibrating (keyframes at {keyframe_hz:g} Hz)")
    with progress.library_output():
        estimate = calibrate(session, Options(keyframe_hz=keyframe_hz, progress=not progress.quiet))
    progress.say("calibration done")
    return estimate


def run_calibrate(args: argparse.Namespace) -> int:
    """calibrate SESSION [--out DIR] [--keyframe-hz HZ] [--data-dir DIR] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    progress = common.Progress(args.quiet)
    path = common.resolve_session_path(args.session, args.data_dir)
    session = common.load(path, progress)
    out = common.out_dir_for(args.out, Path(path).stem)
    estimate = estimate_calibration(session, args.keyframe_hz, progress)
    common.write_estimate(out, session, estimate, progress)
    scores = common.score(session, estimate.calibration, estimate.quat)
    title = f"calibration of {session.name}: {session.n} samples at {session.rate:.1f} Hz → {out}"
    print(calibration_table(estimate.calibration, scores, title))
    return 0


def _read_calibration(path: str) -> Calibration:
    """Calibration from a calibration.json (path as given on the command line)."""
    from imugraph.io.writers import read_calibration_json

    return read_calibration_json(Path(path).expanduser())


def run_smooth(args: argparse.Namespace) -> int:
    """smooth SESSION [--calibration FILE] [--out DIR] [--keyframe-hz HZ] [--data-dir DIR] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    progress = common.Progress(args.quiet)
    # read the calibration first: a bad --calibration fails before any long work
    cal = _read_calibration(args.calibration) if args.calibration else None
    path = common.resolve_session_path(args.session, args.data_dir)
    session = common.load(path, progress)
    out = common.out_dir_for(args.out, Path(path).stem)
    if cal is None:
        estimate = estimate_calibration(session, args.keyframe_hz, progress)
        cal, quat = estimate.calibration, estimate.quat
        common.write_calibration(out, cal, progress)
        source = "estimated"
    else:
        from imugraph.graphs.cpp_smoother import smooth_fixed

        progress.say(f"smoothing with the calibration in {args.calibration}")
        quat = smooth_fixed(session, cal, keyframe_hz=args.keyframe_hz)
        source = f"from {args.calibration}"
    common.write_orientation(out, session.t, quat, progress)
    scores = common.score(session, cal, quat)
    print(f"smoothed orientation of {session.name}: {session.n} samples, calibration {source} → {out}")
    print("\n".join(score_lines(scores)))
    return 0
