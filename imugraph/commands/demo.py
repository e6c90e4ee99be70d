"""`imugraph demo`: the main job on an embedded default, with the answer known.

A simulated session (`imugraph.sim.scenario.distorted_session`: random rotation about all axes, strongly
distorted magnetometer, gyro bias, realistic noise) is calibrated exactly as `imugraph calibrate` would;
the command prints the true against the estimated D, o, dip and gyro bias with the reported marginal
standard deviations, the field-norm error before (raw field over its median norm) and after
(|D⁻¹(b_mag − o)| − 1), and the orientation error against the simulated truth, and writes the same files
as `calibrate`.
"""

from __future__ import annotations

import argparse

from imugraph.commands import common
from imugraph.commands.calibrate import estimate_calibration
from imugraph.commands.report import comparison_table


def run_demo(args: argparse.Namespace) -> int:
    """demo [--out DIR] [--seed N] [--duration S] [--rate HZ] [--keyframe-hz HZ] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    from imugraph.cli import DEMO_MIN_DURATION_S
    from imugraph.errors import SessionError
    from imugraph.sim.scenario import distorted_session

    if args.duration < DEMO_MIN_DURATION_S:     # checked before any output folder is made
        raise SessionError("demo", "duration", f"{args.duration:g} s",
                           f"at least {DEMO_MIN_DURATION_S:g} s (--duration): a shorter simulated motion holds too "
                           "little rotation to calibrate the magnetometer")
    progress = common.Progress(args.quiet)
    progress.say(f"simulating {args.duration:g} s at {args.rate:g} Hz (seed {args.seed}), distorted magnetometer")
    session, truth = distorted_session(args.seed, args.duration, args.rate)
    out = common.out_dir_for(args.out, "demo")
    estimate = estimate_calibration(session, args.keyframe_hz, progress)
    common.write_estimate(out, session, estimate, progress)
    scores = common.score(session, estimate.calibration, estimate.quat)
    title = (f"demo: simulated session, {args.duration:g} s at {args.rate:g} Hz, seed {args.seed} → {out}\n"
             "before: the simulator's truth; after: the estimate")
    print(comparison_table(estimate.calibration, truth, scores, title))
    return 0
