"""Shortest `imugraph demo --duration` that calibrates: which (duration, seed) pass the ML calibration.

Runs exactly what `imugraph demo` runs (sim.scenario.distorted_session, then commands.calibrate's
estimate_calibration with the default keyframe rate) for each duration and seed and prints, per run,
"ok" with the orientation RMS vs the simulated truth, or the error class and its first words.
The demo's minimum duration (commands/demo.py, MIN_DEMO_S) is chosen from this table.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/f21a_demo_min_duration.py --durations 10,15,20,30 --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", default="10,15,20,30")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--rate", type=float, default=100.0)
    args = ap.parse_args()

    from imugraph.commands.calibrate import estimate_calibration
    from imugraph.commands.common import Progress, score
    from imugraph.errors import ImugraphError
    from imugraph.sim.scenario import distorted_session

    print("duration_s seed result cpu_s")
    for dur in (float(x) for x in args.durations.split(",")):
        for seed in (int(x) for x in args.seeds.split(",")):
            c0 = time.process_time()
            try:
                session, _ = distorted_session(seed, dur, args.rate)
                est = estimate_calibration(session, 5.0, Progress(quiet=True))
                rms = score(session, est.calibration, est.quat).orientation_rms_deg
                result = f"ok orientation_rms_deg={rms:.2f}" if rms is not None and np.isfinite(rms) else "ok"
            except ImugraphError as exc:
                result = f"{type(exc).__name__}: {' '.join(str(exc).split()[:12])}"
            print(f"{dur:g} {seed} {result} {time.process_time() - c0:.1f}", flush=True)


if __name__ == "__main__":
    main()
