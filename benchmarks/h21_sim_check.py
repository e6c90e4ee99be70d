"""Issue 4a guard for the knee-gain thigh model (imugraph.factors.knee_sta, session 21 helper H): the simulated
17-IMU motions (no soft-tissue artefact: the true gain is 0) solved with the default model and with the option, same
simulated sessions, worst joint over the seeds (target ≤ 2°) — benchmarks/body_sim_accuracy.py's run_case and
seed_summary, with the option's BodyOptions fields as opts_kw.

    .venv/bin/python benchmarks/h21_sim_check.py [--seeds 0,1,2,3,4] [--motions ...] [--mag both|off|on]
        [--mode two-stage|graph] [--apply gain|offset+gain] [--tau 2] [--turn hinge|cardan] [--screw-home C]
        [--out h21_sim_check.json]

Writes bench_out/<out> (records per solve, seed tables per variant, the estimated gains).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_bench import MOTIONS  # noqa: E402
from benchmarks.body_sim_accuracy import SEED_COLUMNS, run_case, seed_summary  # noqa: E402
from benchmarks.common import print_table  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motions", default=",".join(MOTIONS))
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--mag", choices=("both", "off", "on"), default="both")
    ap.add_argument("--mode", default="two-stage", choices=("two-stage", "graph"))
    ap.add_argument("--apply", default="gain", choices=("gain", "offset+gain"))
    ap.add_argument("--tau", default="2", help="knee_gain_offset_tau_s, s, or 'none'")
    ap.add_argument("--turn", default="hinge", choices=("hinge", "cardan"), help="knee_gain_turn")
    ap.add_argument("--screw-home", type=float, default=0.0, help="knee_gain_screw_home, rad/rad")
    ap.add_argument("--out", default="h21_sim_check.json")
    a = ap.parse_args(argv)
    mags = {"both": [False, True], "off": [False], "on": [True]}[a.mag]
    kg = {"knee_gain_segments": ("RightUpperLeg", "LeftUpperLeg"), "knee_gain_mode": a.mode,
          "knee_gain_apply": a.apply, "knee_gain_offset_tau_s": None if a.tau == "none" else float(a.tau),
          "knee_gain_turn": a.turn, "knee_gain_screw_home": a.screw_home}
    if a.mode == "graph":
        kg["hinges"] = ("RightLowerLeg", "LeftLowerLeg")
    variants = {"default": {}, "knee-gain": kg}
    records = {v: [] for v in variants}
    for name in a.motions.split(","):
        for seed in (int(s) for s in a.seeds.split(",")):
            for v, kw in variants.items():
                print(f"{v}:", flush=True)
                recs = run_case(name, seed, None, False, mags, [None], opts_kw=kw)
                for r in recs:
                    gi = r.setdefault("knee_gain", None)        # res.info["knee_gain"] (run_case)
                    if gi:
                        print("    gains " + ", ".join(f"{n} {d['gain']:+.3f}" for n, d in gi.items()))
                records[v] += recs
    tables = {}
    for v, recs in records.items():
        tables[v] = seed_summary(recs)
        print(f"\n{v}")
        print_table(tables[v], SEED_COLUMNS)
    payload = {"options": kg,                                          # tuples → lists in write_json (json_ready)
               "over_seeds": {v: [dict(zip(SEED_COLUMNS, r)) for r in t] for v, t in tables.items()},
               "records": {v: [{k: r[k] for k in ("label", "seed", "use_mag", "row", "seconds", "knee_gain")} for r in recs]
                           for v, recs in records.items()},
               "command": "benchmarks/h21_sim_check.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    print(f"\nwrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
