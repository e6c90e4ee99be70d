"""Session 21 (helper N): side checks of the neck options (imugraph.graphs.body_neck) — real walk and speed.

1. Real walk (gaittoolbox rawimu, lower body, benchmarks/gaittoolbox_walk.py `ours`): the default model and
   the neck options (unsensed_bend=("Head",), lever_prior_frame="lumped") on the same recording, without and
   with magnetometers; the largest difference between the two outputs' segment quaternions (the lower body
   has no neck and no lumped joint, so both options must leave it untouched) and the LM passes.
2. Speed (benchmarks/body_speed.py `make_session`: 17 IMUs × DURATION s at 60 Hz, the Xsens walk ping-ponged,
   its unsensed segments on the ties): batch CPU time and accuracy, default vs the neck options (and the same
   with lever_pass_iterations 1, and with lever_pass_lumped_sigma_m 5 mm), one solve each in the same process.

    .venv/bin/python benchmarks/n21_neck_checks.py [--duration 60] [--skip-walk] [--out n21_neck_checks.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_sim_accuracy import NECK_VARIANTS  # noqa: E402
from benchmarks.output import write_json  # noqa: E402

TIES, NECK = NECK_VARIANTS["tie"], NECK_VARIANTS["bend+lumped"]     # explicit: the defaults are bend+lumped1 since a3049c8
NECK5, NECK1 = NECK_VARIANTS["bend+lumped5"], NECK_VARIANTS["bend+lumped1"]


def walk_check() -> dict:
    from benchmarks.gaittoolbox_walk import ours, walk_data
    found = walk_data()
    if found is None:
        return {"skipped": "gaittoolbox walk data absent"}
    root = found[0]
    out = {}
    for use_mag in (False, True):
        q0, i0 = ours(root, use_mag, (), extra=TIES)
        q1, i1 = ours(root, use_mag, (), extra=NECK)
        diff = max(float(np.max(np.abs(np.abs(np.sum(q0[n] * q1[n], axis=1)) - 1.0))) for n in q0)
        out["mag" if use_mag else "no-mag"] = {"max_1_minus_abs_dot": diff, "iterations_default": i0["iterations"],
                                                "iterations_neck": i1["iterations"]}
        print(f"  walk {'mag' if use_mag else 'no-mag'}: max |1 − |q0·q1|| {diff:.2e}; passes "
              f"{i0['iterations']} vs {i1['iterations']}", flush=True)
    return out


def speed_check(duration: float) -> dict:
    from benchmarks.body_speed import accuracy, make_session
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions

    sess, skel, nom, psi0 = make_session(duration)
    out = {}
    for name, kw in (("default", TIES), ("neck", NECK), ("neck_1it", NECK1), ("neck5", NECK5)):
        opts = BodyOptions(placements=nom, npose_heading_deg=psi0, **kw)
        c0 = time.process_time()
        res = solve_body_batch(sess, opts)
        cpu = time.process_time() - c0
        acc = accuracy(sess, skel, res)
        out[name] = {"cpu_s": cpu, "iterations": [p["iterations"] for p in res.info["passes"]],
                     "worst_joint_deg": acc["worst_joint_deg"], "worst_relpos_cm": acc["worst_relpos_cm"]}
        print(f"  speed {name}: {cpu:.1f} s CPU, passes {out[name]['iterations']}, worst joint "
              f"{acc['worst_joint_deg']:.2f}°, worst relpos {acc['worst_relpos_cm']:.2f} cm", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--skip-walk", action="store_true")
    ap.add_argument("--out", default="n21_neck_checks.json")
    a = ap.parse_args(argv)
    payload = {"command": "benchmarks/n21_neck_checks.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "load_avg": os.getloadavg()}
    if not a.skip_walk:
        payload["walk"] = walk_check()
    payload["speed"] = speed_check(a.duration)
    print(f"wrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
