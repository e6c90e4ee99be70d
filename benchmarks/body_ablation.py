"""Issue 4c: ablation of the biomechanical model on simulated 17-IMU sessions (set-up of issue 4a).

One simulated session per motion and seed (benchmarks/body_bench.py), solved by the batch estimator with:
    full                  the whole model (BodyOptions defaults)
    no_joints             without the joint-connection factors (B2); the estimator then has no lever arms
                          either, each sensor is a free IMU with its own preintegration
    no_levers             joints kept, the sensor-to-segment position factors (B3: lever-arm priors) dropped
    nominal_bRs (post hoc) the full solution, but each segment orientation from its sensor's with the NOMINAL
                          mounting rotation (imugraph.sim.body.nominal_placement, i.e. without the random up
                          to 30° placement error) instead of the estimated one: what skipping the
                          sensor-to-segment rotation estimate costs
How a factor is dropped is printed and stored: BodyOptions.use_joints / use_levers when the estimator has
them, else the factor's σ raised to 1 km (see body_bench.ablation_options). Scores as in 4a.

    .venv/bin/python benchmarks/body_ablation.py [--motions cmu131_02] [--seeds 0] [--duration S] [--lower]
        [--mag] [--tie] [--bias-walk SIGMA]

Writes bench_out/body_ablation.json.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_bench import (SUMMARY_COLUMNS, ablation_options, motion_path, simulated_session,  # noqa: E402
                                   summary_row)
from benchmarks.common import print_table  # noqa: E402
from benchmarks.output import write_json  # noqa: E402

VARIANTS = ("full", "no_joints", "no_levers")


def with_nominal_rotation(result, skel):
    """The result with nRb = nRs·bRs_nomᵀ (nRs = nRb_est·bRs_est, bRs_nom the nominal mounting), positions by FK."""
    from imugraph.body.skeleton import fill_unsensed
    from imugraph.geometry import quat_conj, quat_mul, rotmat_to_quat
    from imugraph.sim.body import nominal_placement

    q = {}
    for n, p in result.placements.items():
        q_s = quat_mul(result.n_quat[:, skel.index(n)], rotmat_to_quat(np.asarray(p["bRs"], float)))
        q[n] = quat_mul(q_s, quat_conj(rotmat_to_quat(nominal_placement(skel, n).bRs)))
    n_quat = fill_unsensed(skel, q)
    return SimpleNamespace(names=result.names, n_quat=n_quat, n_pos=skel.forward_kinematics(n_quat, result.n_pos[:, 0]))


def main(argv=None) -> int:
    from imugraph.body.evaluate import score_against_truth
    from imugraph.graphs.body import solve_body_batch

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motions", default="cmu131_02")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--lower", action="store_true")
    ap.add_argument("--mag", action="store_true", help="all variants with magnetometers")
    ap.add_argument("--tie", action="store_true", help="truth's unsensed segments follow the estimator's ties")
    ap.add_argument("--bias-walk", type=float, default=0.0, metavar="SIGMA",
                    help="gyro bias random walk, rad/s/√s (default 0: constant biases)")
    ap.add_argument("--out", default="body_ablation.json", help="file name in bench_out/")
    a = ap.parse_args(argv)
    records = []
    for name in a.motions.split(","):
        if not motion_path(name).exists():
            print(f"  {name}: absent, skipped")
            continue
        for seed in (int(s) for s in a.seeds.split(",")):
            skel, session, mask = simulated_session(name, seed, a.duration, a.lower, tie=a.tie,
                                                    bias_walk=a.bias_walk)
            for variant in VARIANTS:
                opts, how = ablation_options(variant, use_mag=a.mag)
                t0 = time.perf_counter()
                try:
                    res = solve_body_batch(session, opts)
                except Exception as exc:            # an ablated model may be singular: record it, go on
                    print(f"  {name} s{seed} {variant}: failed ({type(exc).__name__}: {str(exc)[:120]})")
                    records.append({"motion": name, "seed": seed, "variant": variant, "how": how, "error": str(exc)})
                    continue
                secs = time.perf_counter() - t0
                variants = [(variant, res, how)]
                if variant == "full":
                    variants.append(("nominal_bRs (post hoc)", with_nominal_rotation(res, skel), "bRs = nominal"))
                for label, r, h in variants:
                    sc = score_against_truth(r, session.truth, skel, mask)
                    row = summary_row(f"{name} s{seed} {label}", sc, secs)
                    records.append({"motion": name, "seed": seed, "variant": label, "how": h, "scores": sc,
                                    "seconds": secs, "row": row})
                    print(f"  {row['case']} ({h}): joint max {row['joint_max_deg']:.2f}° mean "
                          f"{row['joint_mean_deg']:.2f}°, position RMS {row['pos_rms_cm']:.2f} cm, {secs:.1f} s",
                          flush=True)
    ok = [r for r in records if "row" in r]
    if not ok:
        return 1
    print()
    print_table([r["row"] for r in ok], SUMMARY_COLUMNS)
    payload = {"issue": "4c", "use_mag": a.mag, "tie_unsensed": a.tie, "gyro_bias_walk": a.bias_walk,
               "lower_body": a.lower,
               "duration": a.duration,
               "command": "benchmarks/body_ablation.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "records": [{k: v for k, v in r.items() if k != "row"} for r in records]}
    print(f"\nwrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
