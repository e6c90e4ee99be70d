"""H6: the accelerometer's κ_a estimated per recording (Options.estimate_acc_rate_error, calibration/acc_rate.py)
on BROAD trials: κ_a per ML round (bounded estimate and free maximiser), and total / inclination / heading RMS
error beside the plain model. Writes bench_out/h6_acc_rate.json.

    .venv/bin/python benchmarks/h6_acc_rate.py [TRIAL_NUMBERS,...] [--opt FIELD=VALUE ...]

(--opt applies to both runs; the variant adds estimate_acc_rate_error=True.)
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts, print_table  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def kappa_trace(est) -> list[dict]:
    """κ_a, the free κ_ml and the log-likelihood gain over s = 0 of each ML round (the calibration's history)."""
    return [h["acc_rate_error"] for h in est.info["history"] if "acc_rate_error" in h]


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = pop_opts(argv)
    base = parse_options(opts)
    variant = replace(base, estimate_acc_rate_error=True)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    rows = []
    for num, s, mask in iter_broad(select):
        e0 = calibrate(s, base, allow_weak=True)
        e1 = calibrate(s, variant, allow_weak=True)
        p0, p1 = error_parts(e0.quat, s, mask), error_parts(e1.quat, s, mask)
        tr = kappa_trace(e1)
        rows.append({"trial": s.name, "base": round(p0[0], 3), "variant": round(p1[0], 3),
                     "diff": round(p1[0] - p0[0], 3), "incl_base": round(p0[1], 3), "incl_var": round(p1[1], 3),
                     "head_base": round(p0[2], 3), "head_var": round(p1[2], 3),
                     "kappa_a": round(tr[-1]["kappa_a"], 4) if tr else None,
                     "kappa_ml": round(tr[-1]["kappa_ml"], 4) if tr else None,
                     "gain": round(tr[-1]["loglik_gain"], 1) if tr else None,
                     "rounds_base": len(e0.info["history"]), "rounds": len(e1.info["history"]),
                     "trace": [round(t["kappa_ml"], 4) for t in tr]})
        print(rows[-1], flush=True)
    if not rows:
        print(f"h6_acc_rate: no BROAD trial matches {argv[0]!r}", file=sys.stderr)
        return 2
    print_table(rows, [k for k in rows[0] if k != "trace"])
    write_json("h6_acc_rate.json", {"options": opts, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
