"""The `imugraph` command line (DESIGN.md, "Command line").

    imugraph calibrate SESSION [--out DIR] [--keyframe-hz 5]
    imugraph smooth SESSION [--calibration FILE] [--out DIR] [--keyframe-hz 5]
    imugraph stream SESSION [--out DIR] [--lag S] [--bootstrap-s 30] [--calibration FILE] [--keyframe-hz 5]
    imugraph batch SESSIONS... --out DIR [--overwrite] [--scheduler ADDRESS] [--workers N] [--keyframe-hz 5]
    imugraph demo [--out DIR] [--seed 0] [--duration 120] [--rate 100]
    imugraph simulate --out FILE.npz [--seed 0] [--duration 120] [--rate 100]
    imugraph mocap SESSION [--out DIR] [--lag S] [--mag] [--hinges knees,elbows]
    imugraph diagnose SESSION [--out DIR] [--effects NAMES] [--seed 0] [--npose T0,T1]
    imugraph bench diagnose [--trials 01,02,...] [--sims 2] [--n 2] [--duration 60] [--out DIR]

Every command takes --out and --quiet; calibrate and smooth take --data-dir (a SESSION that does not
exist as given is looked up there; default $IMUGRAPH_DATA, else ../shared/data). Results go to stdout,
progress lines to stderr. Errors raised on purpose (`ImugraphError`, unreadable or unwritable files)
print one line `imugraph: error: <message>` on stderr and exit with 2; Ctrl-C exits with 130; a closed
stdout pipe (`imugraph calibrate … | head`) exits quietly with 141 (128 + SIGPIPE, what a shell reports).
`batch` exits with 1 when some sessions failed (each reported on its own line; the others still ran).
The heavy modules are imported by the command that needs them, so `--help` answers at once.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

from imugraph.errors import ImugraphError

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141              # 128 + SIGPIPE, as a shell reports a command killed by a closed pipe

# command → (module in imugraph.commands, function taking the parsed arguments, returning the exit code)
COMMANDS = {
    "calibrate": ("calibrate", "run_calibrate"),
    "smooth": ("calibrate", "run_smooth"),
    "stream": ("stream", "run_stream"),
    "batch": ("batch", "run_batch_command"),
    "demo": ("demo", "run_demo"),
    "simulate": ("simulate", "run_simulate"),
    "diagnose": ("diagnose", "run_diagnose"),
    "bench": ("bench", "run_bench"),
    "mocap": ("mocap", "run_mocap"),
}


def _positive(kind: type):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"{text} is not > 0")
        return value
    return parse


def _common(p: argparse.ArgumentParser, out_help: str, data_dir: bool = False) -> None:
    p.add_argument("--out", metavar="DIR", default=None, help=out_help)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    if data_dir:
        p.add_argument("--data-dir", metavar="DIR", default=None,
                       help="where to look for SESSION when it does not exist as given "
                            "(default: $IMUGRAPH_DATA, else ../shared/data)")


def _keyframes(p: argparse.ArgumentParser, default: float = 5.0) -> None:
    p.add_argument("--keyframe-hz", type=_positive(float), default=default, metavar="HZ",
                   help=f"orientation states per second (every sample is still used; default {default:g})")


def _allow_weak(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allow-weak", action="store_true",
                   help="when the data do not identify the calibration (too little rotation), write a "
                        "regularised estimate marked identifiable: false instead of failing")


def _allow_gaps(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allow-gaps", action="store_true",
                   help="accept time gaps longer than 5 median steps as samples that never arrived (the gap model "
                        "bridges them) instead of refusing the session; NPZ files may declare them in a key 'gaps'")


def _gyro_scale(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--gyro-scale", dest="gyro_scale", action="store_const", const=True, default=None,
                   help="estimate the gyro scale/misalignment (the default: from gravity-only stretches, only "
                        "when the data hold enough turns and the estimate settles)")
    g.add_argument("--no-gyro-scale", dest="gyro_scale", action="store_const", const=False,
                   help="do not estimate the gyro scale/misalignment (faster)")


# shortest `demo --duration` that calibrates: 30 of 30 seeds at 20 s, 25 of 30 at 15 s, 0 of 8 at 10–11 s
# (benchmarks/f21a_demo_min_duration.py --durations 15,20 --seeds 0,...,29)
DEMO_MIN_DURATION_S = 20.0


def _simulation(p: argparse.ArgumentParser, duration_help: str = "length in s (default 120)") -> None:
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=_positive(float), default=120.0, metavar="S", help=duration_help)
    p.add_argument("--rate", type=_positive(float), default=100.0, metavar="HZ", help="sampling rate (default 100)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="imugraph", description="IMU sensor fusion with factor graphs: magnetometer calibration with "
        "inertial sensors (Kok & Schön), orientation smoothing (batch, incremental, many sessions), body motion "
        "capture from several IMUs, and sim-to-real gap diagnosis.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    session_help = "session file (.npz, .mat, .hdf5, .csv, .txt) or x-IMU3 folder"
    default_out = "output folder (default: imugraph_out/<session stem>)"

    p = sub.add_parser("calibrate", help="calibrate the magnetometer and smooth the orientation",
                       description="Writes calibration.json, orientation.npz, calibration.png, heading.png.")
    p.add_argument("session", metavar="SESSION", help=session_help)
    _common(p, default_out, data_dir=True)
    _keyframes(p)
    _allow_weak(p)
    _gyro_scale(p)
    _allow_gaps(p)

    p = sub.add_parser("smooth", help="smoothed orientation (with a known or estimated calibration)",
                       description="Writes orientation.npz (and calibration.json when it is estimated).")
    p.add_argument("session", metavar="SESSION", help=session_help)
    p.add_argument("--calibration", metavar="FILE", default=None, help="calibration.json to use instead of estimating one")
    p.add_argument("--no-field", action="store_true",
                   help="with --calibration: no nav-field perturbation d_k (the C++-only smoother of earlier versions)")
    _common(p, default_out, data_dir=True)
    _keyframes(p)
    _allow_gaps(p)

    p = sub.add_parser("stream", help="incremental orientation: samples in arrival order through iSAM2",
                       description="Writes orientation.npz (smoothed), orientation_filtered.npz (available "
                       "when each sample arrived), calibration.json, calibration_history.json and timing.json. The "
                       "calibration starts from a batch bootstrap on the first seconds (or --calibration) and is "
                       "re-estimated online (D, o by least squares every 2 s) unless --fixed-calibration.")
    p.add_argument("session", metavar="SESSION", help=session_help)
    p.add_argument("--lag", type=_positive(float), default=None, metavar="S",
                   help="fixed-lag smoother keeping S seconds (default: iSAM2 over the whole stream)")
    p.add_argument("--bootstrap-s", type=_positive(float), default=30.0, metavar="S",
                   help="seconds calibrated in batch before streaming (default 30; the window grows while it holds "
                        "too little rotation to identify the calibration, up to the whole recording unless "
                        "--bootstrap-max-s)")
    p.add_argument("--bootstrap-max-s", type=_positive(float), default=None, metavar="S",
                   help="cap the bootstrap's growth at S seconds; at the cap calibrate's regularised weak fallback "
                        "is used (default: no cap)")
    p.add_argument("--bootstrap-regrow", action="store_true",
                   help="stream from a short bootstrap (capped at --bootstrap-max-s, else at --bootstrap-s) and keep "
                        "growing it in the background: a window that identifies the calibration (or a longer weak "
                        "one) is switched to once calibrated and replayed, without a heading jump; growth goes on "
                        "until a window --bootstrap-regrow-confirm times longer agrees (a differing one is switched "
                        "to). Switches are listed in timing.json 'regrow' (default: off, the bootstrap grows first)")
    p.add_argument("--bootstrap-regrow-grow", type=_positive(float), default=1.2, metavar="F",
                   help="with --bootstrap-regrow: each window F times the last (default 1.2)")
    p.add_argument("--bootstrap-regrow-confirm", type=_positive(float), default=2.0, metavar="C",
                   help="with --bootstrap-regrow: stop growing when a window C times the current calibration's "
                        "agrees with it (default 2)")
    p.add_argument("--bootstrap-regrow-latency", type=_positive(float), default=None, metavar="S",
                   help="with --bootstrap-regrow: switch S seconds of stream time after a window's last row instead "
                        "of after the measured CPU time of its calibration and replay (repeatable runs)")
    p.add_argument("--calibration", metavar="FILE", default=None,
                   help="start calibration.json instead of the bootstrap (re-estimated online unless --fixed-calibration; the smoothed output of a full iSAM2 run uses the streamed one)")
    p.add_argument("--fixed-calibration", action="store_true",
                   help="hold the start calibration fixed (no online re-estimation of D and o)")
    p.add_argument("--lag-solver", choices=("chain", "incremental", "batch"), default="chain",
                   help="fixed-lag solver: iSAM2 with a once-a-second window re-elimination (chain, default; "
                   "docs/stream.md), gtsam's incremental fixed-lag smoother, or its batch one")
    p.add_argument("--calib-states", action=argparse.BooleanOptionalAction, default=None,
                   help="D, o and the dip as states of the incremental graph instead of the periodic refit")
    p.add_argument("--disturb", action=argparse.BooleanOptionalAction, default=None,
                   help="detect magnetic disturbance windows causally and keep them out of the calibration")
    p.add_argument("--disturb-offsets", action=argparse.BooleanOptionalAction, default=None,
                   help="each detected window its own hard-iron offset; the state seen most so far is 'normal' "
                   "(needs --calib-states --disturb)")
    p.add_argument("--weak-prior", action=argparse.BooleanOptionalAction, default=None,
                   help="when D, o are not identifiable, hold them with the batch's weak prior")
    p.add_argument("--calib-json-end-graph", action=argparse.BooleanOptionalAction, default=None,
                   help="calibration.json holds what the end-of-stream graph used (streamed θ, each window's final "
                   "offset as a disturbance), so `smooth --calibration` reproduces orientation.npz (full iSAM2 only)")
    _common(p, default_out, data_dir=True)
    _keyframes(p, default=10.0)        # StreamOptions.keyframe_hz: what the stream benchmarks measure
    _allow_gaps(p)

    p = sub.add_parser("batch", help="calibrate and smooth many sessions in parallel on Dask",
                       description="One folder DIR/<name> per session with the files of calibrate (name: the "
                       "session stem, or the shortest path suffix telling equal stems apart, e.g. a-s and b-s for "
                       "a/s.npz and b/s.npz), and DIR/summary.json + summary.csv. Exit status 1 when any session "
                       "failed.")
    p.add_argument("sessions", metavar="SESSION", nargs="+", help=session_help + " (a file given twice runs once)")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="output folder (one subfolder per session): new or empty, else refused unless --overwrite")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a DIR that holds an earlier run; its session folders that get no result from "
                        "this run are removed (docs/batch.md)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or lines on stderr")
    p.add_argument("--data-dir", metavar="DIR", default=None,
                   help="where to look for a SESSION that does not exist as given "
                        "(default: $IMUGRAPH_DATA, else ../shared/data)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="address of a running dask scheduler (e.g. tcp://host:8786; its workers must see the "
                        "session files and DIR); default: a local cluster of worker processes")
    p.add_argument("--workers", type=_positive(int), default=None, metavar="N",
                   help="worker processes of the local cluster (default: CPU count, at most one per session)")
    _keyframes(p)
    _allow_weak(p)
    _gyro_scale(p)

    p = sub.add_parser("demo", help="calibrate a simulated distorted magnetometer and compare with the truth",
                       description="Writes the same files as calibrate and prints true vs estimated values.")
    _common(p, "output folder (default: imugraph_out/demo)")
    _simulation(p, f"length in s (default 120, at least {DEMO_MIN_DURATION_S:g}: shorter motions hold too little "
                   "rotation to calibrate)")
    _keyframes(p)

    p = sub.add_parser("simulate", help="write a simulated session (NPZ: gyr, acc, mag, t, quat)",
                       description="Random rotation about all axes, distorted magnetometer, gyro bias, noise.")
    p.add_argument("--out", metavar="FILE.npz", required=True,
                   help="session file to write: .npz (with the truth), or .csv (the imugraph CSV columns with the true "
                        "orientation quat_w..z; without the calibration truth true_D, true_o, …)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    _simulation(p)
    p.add_argument("--effect", metavar="NAME", action="append", default=None,
                   help="inject an unmodelled effect of the diagnosis library into the simulated session (its "
                        "inject(), seeded from --seed; repeatable or comma-separated; see imugraph diagnose)")

    p = sub.add_parser("mocap", help="body motion from several IMUs on one body (joints, sensor-to-segment)",
                       description="Writes mocap.npz, joint_angles.csv, motion.bvh, joint_angles.png, "
                       "stick_figures.png, mocap_info.json (with --lag also mocap_filtered.npz, timing.json).")
    from imugraph.commands.mocap import add_arguments as mocap_arguments
    mocap_arguments(p)

    p = sub.add_parser("diagnose", help="where the sim-to-real gap lies and which unmodelled effect explains it",
                       description="Writes diagnosis.json, diagnosis.md, gap_over_time.png, residuals.png.")
    p.add_argument("session", metavar="SESSION", help=session_help + ", or a body session (any mocap SESSION: folder "
                   "with session.json, gaittoolbox rawimu folder, folder of x-IMU3 export folders, .mvnx file)")
    _common(p, default_out, data_dir=True)
    _keyframes(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the simulations (default 0)")
    p.add_argument("--effects", metavar="NAMES", default=None,
                   help="comma-separated effect names to try (default: all)")
    p.add_argument("--npose", metavar="T0,T1", default=None,
                   help="body sessions: the static N-pose window in the session's own time, s, as mocap --npose "
                        "(default: detected, the common rest of all sensors at the start; none found: refused)")

    p = sub.add_parser("bench", help="validation benchmarks (bench diagnose: the diagnosis harness)")
    bsub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    pd = bsub.add_parser("diagnose", help="inject effects into real and simulated sessions, hide the label, "
                         "score the diagnosis (confusion matrix, window IoU, gap shrink)",
                         description="Writes harness.json and harness.md in --out.")
    from imugraph.diagnose.bench import add_arguments as bench_diagnose_arguments
    bench_diagnose_arguments(pd)
    return parser


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush of a closed pipe raises nothing."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _error(message: str) -> int:
    print(f"imugraph: error: {' '.join(str(message).split())}", file=sys.stderr, flush=True)
    return EXIT_ERROR


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run one command.

    Args:
        argv: arguments without the program name (default: sys.argv[1:]).

    Returns:
        Exit code: 0 success, 2 bad usage or bad input (one line on stderr), 130 interrupted.
    """
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:           # --help (0) or a usage error (2), already printed by argparse
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_ERROR
    module, function = COMMANDS[args.command]
    try:
        run = getattr(importlib.import_module(f"imugraph.commands.{module}"), function)
        code = int(run(args))
        sys.stdout.flush()              # a closed pipe shows here, not in the interpreter's exit flush
        return code
    except BrokenPipeError:             # stdout (or stderr) read by e.g. `| head`, which stopped reading
        _silence_stdout()
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        print("imugraph: interrupted", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    except ImugraphError as exc:
        return _error(str(exc))
    except OSError as exc:              # a file that vanished or could not be written mid-way
        where = f"{exc.filename}: " if exc.filename else ""
        return _error(f"{where}{exc.strerror or exc}")


if __name__ == "__main__":
    sys.exit(main())
