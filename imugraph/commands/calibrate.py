"""`imugraph calibrate` and `imugraph smooth`.

calibrate SESSION: maximum-likelihood magnetometer calibration with the inertial sensors (Kok & Schön,
`imugraph.calibration.ml.calibrate`), writing calibration.json, orientation.npz, calibration.png and
heading.png, and printing the result table.
smooth SESSION: the smoothed orientation only — with a known calibration (--calibration FILE, GTSAM C++
factors, `imugraph.graphs.cpp_smoother.smooth_fixed`), or estimated on the way (then calibration.json too).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Union

from imugraph.commands import common
from imugraph.calibration.options import Options
from imugraph.calibration.result import Calibration
from imugraph.commands.report import calibration_table, score_lines
from imugraph.io.session import Session

if TYPE_CHECKING:
    from imugraph.calibration.ml import Estimate


@dataclass(frozen=True)
class CalibrateOptions:
    """Settings of one `calibrate` run (plain values: picklable, sent to batch workers).

    Attributes:
        keyframe_hz: orientation states per second (every sample is still used).
        allow_weak: when the data do not identify D and o, return a regularised estimate (coverage
            "identifiable": false) instead of raising CalibrationError.
        gyro_scale: estimate the gyro scale/misalignment matrix E (ml.Options.gyro_map, gated; BROAD
            mean 0.83° → 0.77°, one more ML round where the gates pass); None: the library default
            (ml.Options().gyro_map, on), True/False: --gyro-scale / --no-gyro-scale.
        allow_gaps: --allow-gaps, time gaps declared as missing samples (`imugraph.io.readers.load_session`).
    """

    keyframe_hz: float = 5.0
    allow_weak: bool = False
    gyro_scale: Optional[bool] = None
    allow_gaps: bool = False


def estimate_calibration(session: Session, keyframe_hz: float, progress: common.Progress,
                         allow_weak: bool = False, gyro_scale: Optional[bool] = None) -> "Estimate":
    """Run the ML calibration (`imugraph.calibration.ml.calibrate`), its per-round lines on stderr.

    Args:
        session: the recording.
        keyframe_hz: orientation states per second.
        progress: progress stream (quiet: the ML loop prints nothing either).
        allow_weak: see `CalibrateOptions.allow_weak`.
        gyro_scale: see `CalibrateOptions.gyro_scale`.

    Returns:
        Estimate: calibration, t (N,), quat (N, 4) nRb w,x,y,z, whitened residuals per channel.

    Raises:
        CalibrationError: the data do not allow a calibration (e.g. too little rotation).
    """
    from imugraph.calibration.ml import Options, calibrate

    progress.say(f"calibrating (keyframes at {keyframe_hz:g} Hz)")
    options = Options(keyframe_hz=keyframe_hz, progress=not progress.quiet)
    if gyro_scale is not None:          # else the library default
        options.gyro_map = bool(gyro_scale)
    with progress.library_output():
        estimate = calibrate(session, options, allow_weak=allow_weak)
    progress.say("calibration done")
    return estimate


def calibrate_path(path: Union[str, Path], out_dir: Optional[Union[str, Path]],
                   options: CalibrateOptions = CalibrateOptions(),
                   progress: Optional[common.Progress] = None) -> dict:
    """The whole `calibrate` command on one session file: read, calibrate, write the outputs, score.

    Used by `imugraph calibrate` and, once per session on a worker, by `imugraph batch`.

    Args:
        path: session file or x-IMU3 folder (already resolved).
        out_dir: output folder, created if missing; None for imugraph_out/<session stem>.
        options: keyframe rate and weak-data policy.
        progress: progress stream; default quiet.

    Returns:
        Plain values: session (name), path, out, samples, rate_hz, orientation_rms_deg (RMS error vs the
        session's quat truth over `movement`, degrees; None without truth), norm_before / norm_after
        (field-norm RMS, dimensionless), converged, iterations, identifiable, table (the printed table).

    Raises:
        SessionError: unreadable or invalid session, or an output folder that cannot be created.
        CalibrationError: the data do not allow a calibration (unless options.allow_weak).
    """
    progress = progress or common.Progress(quiet=True)
    path = Path(path)
    session = common.load(path, progress, options.allow_gaps)
    common.check_keyframe_hz(session, options.keyframe_hz)
    # checked writable before the calibration; removed again if still empty when it fails (e.g. too little rotation)
    with common.output_folder(None if out_dir is None else str(out_dir), path.stem) as out:
        estimate = estimate_calibration(session, options.keyframe_hz, progress, options.allow_weak,
                                        options.gyro_scale)
        common.write_estimate(out, session, estimate, progress)
    cal = estimate.calibration
    scores = common.score(session, cal, estimate.quat)
    title = f"calibration of {session.name}: {session.n} samples at {session.rate:.1f} Hz → {out}"
    coverage = cal.coverage if isinstance(cal.coverage, dict) else {}
    return {"session": session.name, "path": str(path), "out": str(out), "samples": int(session.n),
            "rate_hz": float(session.rate), "orientation_rms_deg": scores.orientation_rms_deg,
            "norm_before": float(scores.norm_before), "norm_after": float(scores.norm_after),
            "converged": bool(cal.converged), "iterations": int(cal.iterations),
            "identifiable": bool(coverage.get("identifiable", True)),
            "table": calibration_table(cal, scores, title)}


def run_calibrate(args: argparse.Namespace) -> int:
    """calibrate SESSION [--out DIR] [--keyframe-hz HZ] [--allow-weak] [--gyro-scale | --no-gyro-scale]
    [--data-dir DIR] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    progress = common.Progress(args.quiet)
    path = common.resolve_session_path(args.session, args.data_dir)
    options = CalibrateOptions(args.keyframe_hz, getattr(args, "allow_weak", False),
                               getattr(args, "gyro_scale", None), getattr(args, "allow_gaps", False))
    print(calibrate_path(path, args.out, options, progress)["table"])
    return 0


def run_smooth(args: argparse.Namespace) -> int:
    """smooth SESSION [--calibration FILE] [--out DIR] [--keyframe-hz HZ] [--data-dir DIR] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    progress = common.Progress(args.quiet)
    if getattr(args, "no_field", False) and not args.calibration:
        from imugraph.errors import ImugraphError
        raise ImugraphError("--no-field: found without --calibration; expected together with --calibration FILE")
    path, session, cal = common.load_with_calibration(args, progress)      # a bad --calibration fails first
    with common.output_folder(args.out, Path(path).stem) as out:     # no empty folder left by a failed run
        return _smooth_into(out, args, session, cal, progress)


def _smooth_into(out: Path, args: argparse.Namespace, session: Session, cal: Optional[Calibration],
                 progress: common.Progress) -> int:
    """run_smooth's body once the session is read: smooth (estimating the calibration when `cal` is None),
    write into `out`, print the scores."""
    if cal is None:
        estimate = estimate_calibration(session, args.keyframe_hz, progress)
        cal, quat = estimate.calibration, estimate.quat
        common.write_calibration(out, cal, progress)
        source = "estimated"
    else:
        from imugraph.graphs.cpp_smoother import smooth_fixed

        progress.say(f"smoothing with the calibration in {args.calibration}")
        # the batch model's nav-field perturbation d_k (Options.field_sigma/field_tau, as calibrate and stream):
        # BROAD 17 trials 0.801° → 0.662° mean vs truth, 0.66 s CPU mean (benchmarks/smooth_field.py all)
        opt = Options()
        field = {} if getattr(args, "no_field", False) else {"field_sigma": opt.field_sigma, "field_tau": opt.field_tau}
        quat = smooth_fixed(session, cal, keyframe_hz=args.keyframe_hz, **field)
        source = f"from {args.calibration}"
    common.write_orientation(out, session.t, quat, progress)
    scores = common.score(session, cal, quat)
    print(f"smoothed orientation of {session.name}: {session.n} samples, calibration {source} → {out}")
    print("\n".join(score_lines(scores)))
    return 0
