"""Session 21 (helper N21b), issue 4a: side checks of a tighter lumped-joint σ (BodyOptions.lumped_joint_sigma_m).

The same two checks as benchmarks/n21_neck_checks.py, for the variants of benchmarks/body_sim_accuracy.py's
NECK_VARIANTS named on the command line (each on top of today's default model):

1. Speed and accuracy on body_speed's session (benchmarks/body_speed.py `make_session`: 17 IMUs × DURATION s at
   60 Hz, the Xsens walk ping-ponged, its unsensed segments on the ties, so a rigid neck and lumbar are right
   there): batch CPU time, LM passes, worst joint (°) and worst relative position (cm), one solve each.
2. The fixed lag (imugraph.graphs.body_incremental, lag 1 s) on the same session, which uses
   lumped_joint_sigma_m too (it keeps the ties for the neck): worst joint and relative position.

    .venv/bin/python benchmarks/n21b_checks.py [--duration 60] [--variants default,lumped7] [--lag 1] [--mag]
        [--out n21b_checks.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_sim_accuracy import NECK_VARIANTS  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def check(duration: float, variants: list, lag: float | None, use_mag: bool = False) -> dict:
    from benchmarks.body_speed import accuracy, make_session
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_incremental import solve_body_incremental
    from imugraph.graphs.body_model import BodyOptions

    sess, skel, nom, psi0 = make_session(duration)
    out = {}
    for name in variants:
        opts = BodyOptions(placements=nom, npose_heading_deg=psi0, use_mag=use_mag, **NECK_VARIANTS[name])
        c0 = time.process_time()
        res = solve_body_batch(sess, opts)
        cpu = time.process_time() - c0
        acc = accuracy(sess, skel, res)
        rec = {"cpu_s": cpu, "iterations": [p["iterations"] for p in res.info["passes"]],
               "worst_joint_deg": acc["worst_joint_deg"], "worst_relpos_cm": acc["worst_relpos_cm"]}
        print(f"  batch {name}: {cpu:.1f} s CPU, passes {rec['iterations']}, worst joint "
              f"{acc['worst_joint_deg']:.2f}°, worst relpos {acc['worst_relpos_cm']:.2f} cm", flush=True)
        if lag:
            c0 = time.process_time()
            res = solve_body_incremental(sess, opts, lag_s=lag)
            rec["lag_cpu_s"] = time.process_time() - c0
            acc = accuracy(sess, skel, res)
            rec["lag_worst_joint_deg"], rec["lag_worst_relpos_cm"] = acc["worst_joint_deg"], acc["worst_relpos_cm"]
            print(f"  lag {lag:g} s {name}: {rec['lag_cpu_s']:.1f} s CPU, worst joint {acc['worst_joint_deg']:.2f}°, "
                  f"worst relpos {acc['worst_relpos_cm']:.2f} cm", flush=True)
        out[name] = rec
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--variants", default="default,lumped7")
    ap.add_argument("--lag", type=float, default=1.0, help="fixed lag, s (0: batch only)")
    ap.add_argument("--mag", action="store_true", help="with magnetometers (BodyOptions.use_mag)")
    ap.add_argument("--out", default="n21b_checks.json")
    a = ap.parse_args(argv)
    payload = {"command": "benchmarks/n21b_checks.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "load_avg": os.getloadavg(),
               "speed": check(a.duration, a.variants.split(","), a.lag or None, a.mag)}
    print(f"wrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
