"""H7: the gyro-bias random-walk density q estimated per recording (Options.estimate_bias_rw,
calibration/bias_process.py) on BROAD trials, beside the fixed q (Options.bias_rw) and offline VQF, in one run:
total / inclination / heading RMS error (same scoring as broad_published.py: orientation_error over
`movement`), q̂ per ML round, rounds and CPU time. Writes bench_out/h7_bias_process.json.

    .venv/bin/python benchmarks/h7_bias_process.py [TRIAL_NUMBERS,...] [--opt FIELD=VALUE ...]

(--opt applies to both runs; the variant adds estimate_bias_rw=True.)
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts, print_variant_summary  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def q_trace(est) -> list[float]:
    """q̂ (rad/s/√s) of each ML round that estimated it (the calibration's history)."""
    return [h["bias_rw"] for h in est.info["history"] if "bias_rw" in h]


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = pop_opts(argv)
    base = parse_options(opts)
    variant = replace(base, estimate_bias_rw=True)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    rows = []
    for num, s, mask in iter_broad(select):
        c0 = time.process_time()
        e0 = calibrate(s, base, allow_weak=True)
        c1 = time.process_time()
        e1 = calibrate(s, variant, allow_weak=True)
        c2 = time.process_time()
        p0, p1, pv = (error_parts(q, s, mask) for q in (e0.quat, e1.quat, vqf_offline(s)))
        tr = q_trace(e1)
        rows.append({"trial": s.name[:2], "base": round(p0[0], 3), "variant": round(p1[0], 3),
                     "diff": round(p1[0] - p0[0], 3), "offline_vqf": round(pv[0], 3),
                     "incl_base": round(p0[1], 3), "incl_var": round(p1[1], 3), "incl_vqf": round(pv[1], 3),
                     "head_base": round(p0[2], 3), "head_var": round(p1[2], 3),
                     "q_hat": float(f"{tr[-1]:.3g}") if tr else None,
                     "rounds_base": len(e0.info["history"]), "rounds": len(e1.info["history"]),
                     "cpu_base_s": round(c1 - c0, 2), "cpu_var_s": round(c2 - c1, 2),
                     "trace": [float(f"{q:.3g}") for q in tr]})
        print(rows[-1], flush=True)
    if print_variant_summary([{k: v for k, v in r.items() if k != "trace"} for r in rows],
                             "h7_bias_process", argv[0] if argv else "", opts, " + estimate_bias_rw=True") is None:
        return 2
    write_json("h7_bias_process.json", {"options": opts, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
