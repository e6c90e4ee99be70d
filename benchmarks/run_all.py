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
    diagnose_harness.py  blind injections: confusion matrix, window IoU, gap shrink; seeds 0-4 (issue 5)
    stream_vs_batch.py   the stream's smoothed orientation against the batch path              (issue 3)
    stream_arrival.py    late / duplicate / invalid / missing samples on BROAD 01, 06, 34      (issue 3)
    batch_gaps.py        the batch path with the same drops                                    (issue 3)
    qmt_full_body.py     the real 16-IMU full-body recording (no truth: plausibility)          (issue 4)
    t20_rasteiro_diagnose.py  diagnosis of Rasteiro's raw recordings                          (issue 5)
    smooth_field.py      `smooth --calibration` with and without the field perturbation d_k  (issue 2e)
    x19_swap.py          which part of the stream's end model keeps it from the batch        (issue 3)
    diagnose_body.py     body-session diagnosis harness, seeds 0-4                            (issue 5)

Each entry runs the command README.md's "Status at a glance" cites for its row (M23, session 23), with
OPENBLAS_NUM_THREADS=1 (and OMP_NUM_THREADS=1) where the README's command sets it. stream_speed.py runs three
times: the row-118/120/121 command (`--cache DIR`), and row 123's causal scoring (`--no-cal-compare
--score-after-bootstrap`) uncapped and with `--bootstrap-max-s 60`, each to its own bench_out file. DIR is a fresh
temporary folder for this run, shared by stream_speed.py and stream_vs_batch.py (the README's `--cache DIR`): never
a stale cache from an earlier run. body_sim_accuracy.py also runs row 133's neck variants (seeds 0-4 and the
held-out 5-9), diagnose_harness.py and diagnose_body.py once per seed 0-4, each seed to its own bench_out file or
folder. Not run: the README's optional variants in brackets or "for before" (stream_arrival `--kinds drop`,
qmt_full_body `--init nominal`, diagnose_harness `--local-check`).

    .venv/bin/python benchmarks/run_all.py [--list]      (--list: the command lines, nothing run)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
CACHE = "{cache}"                     # replaced by the run's fresh cache folder ("DIR" with --list)
ALL17 = "01,02,04,06,07,10,12,15,16,21,24,26,28,30,32,34,36"
STREAM = ["all", "--lag", "2", "--lag-solver", "chain", "--lag-only", "--no-batch"]      # README issue 3: chain
ONE = True                            # README's command sets OPENBLAS_NUM_THREADS=1

# (script, arguments, one BLAS thread?) — each the README "Status at a glance" command of its row
STEPS = (("peer_table.py", [], False), ("sim_coverage.py", ["50", "60", "100"], False),
         ("broad_published.py", [], False), ("broad_known_distortion.py", [], False),
         ("rasteiro.py", [], False), ("speed.py", [ALL17, "--repeat", "1"], ONE), ("batch_scaling.py", [], ONE),
         ("stream_speed.py", STREAM + ["--cache", CACHE], ONE),                              # rows 118, 120, 121
         ("stream_speed.py", STREAM + ["--no-cal-compare", "--score-after-bootstrap",        # row 123: causal
                                       "--out", "stream_speed_after_bootstrap.json"], ONE),
         ("stream_speed.py", STREAM + ["--no-cal-compare", "--score-after-bootstrap", "--bootstrap-max-s", "60",
                                       "--out", "stream_speed_after_bootstrap60.json"], ONE),
         ("stream_vs_batch.py", ["all", "--config", "session18,default", "--cache", CACHE], ONE),
         ("smooth_field.py", ["all", "--cache", CACHE], ONE),          # README 2e text: the batch cal_NN.pkl above
         ("x19_swap.py", ["all", "--cache", CACHE], ONE),              # row 119's second command
         ("stream_memory.py", ["--minutes", "30"], False),
         ("stream_arrival.py", ["01,06,34"], ONE), ("batch_gaps.py", ["01,06,34", "--ablate"], ONE),
         ("body_sim_accuracy.py", ["--seeds", "0,1,2,3,4"], False),
         ("body_sim_accuracy.py", ["--seeds", "0,1,2,3,4", "--neck", "default,bend+lumped1",           # row 133
                                   "--out", "body_sim_accuracy_neck.json"], False),
         ("body_sim_accuracy.py", ["--seeds", "5,6,7,8,9", "--neck", "default,neck5mf",                # held out
                                   "--out", "body_sim_accuracy_neck_heldout.json"], False),
         ("gaittoolbox_walk.py", ["--ablation", "--lag", "1"], False), ("body_walk_diagnosis.py", [], False),
         ("body_ablation.py", ["--motions", "cmu131_02,xsens", "--bias-walk", "0.002"], False),
         ("body_speed.py", ["--duration", "60", "--modes", "batch,lag"], False),
         ("qmt_full_body.py", ["--init", "auto", "--no-lag"], False),
         ("diagnose_broad.py", ["--trials", "all"], ONE), ("t20_rasteiro_diagnose.py", [], ONE),
         # each seed into its own folder (the default bench_out/diagnose would keep only the last seed's harness.json)
         *(("diagnose_harness.py", ["--n", "2", "--duration", "60", "--seed", str(seed),
                                    "--out", f"bench_out/diagnose_seed{seed}"], ONE) for seed in range(5)),
         *(("diagnose_body.py", ["--hosts", "xsens_lower,cmu_lower,xsens_full,real_walk", "--duration", "20",
                                 "--seed", str(seed), "--out", f"diagnose_body_seed{seed}.json"], False)
           for seed in range(5)))


def command(script: str, args: list[str], cache: str) -> list[str]:
    """The step's argv (python, script, arguments) with the cache placeholder filled in."""
    return [sys.executable, str(HERE / script), *(cache if a == CACHE else a for a in args)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="run_all.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--list", action="store_true", help="print the benchmark command lines without running them")
    args = ap.parse_args(argv)
    rc = 0
    with tempfile.TemporaryDirectory(prefix="run_all_cache_") as cache:
        for script, script_args, one_thread in STEPS:
            cmd = command(script, script_args, "DIR" if args.list else cache)
            env = dict(os.environ, **({"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"} if one_thread else {}))
            if args.list:
                print(("OPENBLAS_NUM_THREADS=1 " if one_thread else "") + " ".join(cmd))
                continue
            print(f"\n=== {script} {' '.join(cmd[2:])} ===", flush=True)
            rc |= subprocess.call(cmd, env=env)
    return rc


if __name__ == "__main__":
    sys.exit(main())
