"""`make bench`: every benchmark, each printing its own table (results also in bench_out/).

    sim_coverage.py      simulated truth within reported std; noise levels         (issue 2a)
    broad_published.py   BROAD trials as published vs offline VQF / VQF + timing   (issue 2c, 2e)
    broad_known_distortion.py  BROAD with a known seeded affine distortion of the magnetometer  (issue 2b)
    rasteiro.py          raw uncalibrated magnetometers vs robot arm: field norm, heading    (issue 2d)
    speed.py             calibrate+smooth / smooth with known calibration vs offline VQF   (issue 2e)
    peer_table.py        the peers alone (checks the metric against the data README)
    batch_scaling.py     `imugraph batch` on the BROAD trials, 1 vs 2 worker processes (issue 3)
    stream_speed.py      `imugraph stream` on the 17 BROAD trials: real-time factor, latency, filtered vs online VQF (issue 3)
    stream_memory.py     30 simulated minutes through the fixed lag: memory growth per minute      (issue 3)
    body_sim_accuracy.py 17-IMU simulations from CMU / Xsens BVH: joint and position errors     (issue 4a)
    gaittoolbox_walk.py  real lower-body walk vs Vicon, beside Xsens MVN; ablation; fixed lag  (issue 4b, 4c)
    body_walk_diagnosis.py  where the real walk's left-hip error comes from                    (issue 4b)
    body_ablation.py     simulation ablation with a drifting gyro bias                          (issue 4c)
    body_speed.py        17 IMUs x 60 s at 60 Hz: batch and fixed lag, time and memory          (issue 4d)
    diagnose_broad.py    diagnosis of disturbed and undisturbed BROAD trials, no labels         (issue 5)
    diagnose_harness.py  blind injections: confusion matrix, window IoU, gap shrink             (issue 5)

    .venv/bin/python benchmarks/run_all.py [--list]      (--list: the command lines, nothing run)
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


STEPS = (("peer_table.py", []), ("sim_coverage.py", ["50", "60", "100"]),
         ("broad_published.py", []), ("broad_known_distortion.py", []),
         ("rasteiro.py", []), ("speed.py", []), ("batch_scaling.py", []),
         ("stream_speed.py", ["all", "--lag", "2", "--lag-solver", "chain", "--lag-only",
                              "--no-batch", "--no-cal-compare"]),     # README issue 3: chain
         ("stream_memory.py", ["--minutes", "30"]),
         ("body_sim_accuracy.py", ["--seeds", "0,1,2,3,4"]),
         ("gaittoolbox_walk.py", ["--ablation", "--lag", "1"]), ("body_walk_diagnosis.py", []),
         ("body_ablation.py", ["--motions", "cmu131_02,xsens", "--bias-walk", "0.002"]),
         ("body_speed.py", ["--duration", "60", "--modes", "batch,lag"]),
         ("diagnose_broad.py", []), ("diagnose_harness.py", ["--n", "2", "--duration", "60"]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="run_all.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--list", action="store_true", help="print the benchmark command lines without running them")
    args = ap.parse_args(argv)
    rc = 0
    for script, script_args in STEPS:
        if args.list:
            print(f"{sys.executable} {HERE / script} {' '.join(script_args)}".rstrip())
            continue
        print(f"\n=== {script} {' '.join(script_args)} ===", flush=True)
        rc |= subprocess.call([sys.executable, str(HERE / script), *script_args])
    return rc


if __name__ == "__main__":
    sys.exit(main())
