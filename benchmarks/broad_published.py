"""Issue 2c: batch smoothing of the published BROAD trials as they are (calibration estimated from each
trial), side by side with offline VQF and VQF, scored over `movement` at the best time shift (±3 samples)
and best constant heading offset. Prints a table and the means; writes bench_out/broad_published.json.

    .venv/bin/python benchmarks/broad_published.py [TRIAL_NUMBERS,...] [--keyframe-hz HZ] [--opt FIELD=VALUE ...]

Beside each trial's two RMS errors, `diff_ci95` is a 95 % interval of imugraph's RMS minus offline VQF's from a
moving-block bootstrap over the scored samples (10 s blocks, 2000 resamples, seed 0; each system at its own
alignment): how far "worse" or "better" is a measured difference on that trial, not only the sign. Evaluation
only (the optical reference is resampled, nothing is refitted).

--opt sets any field of imugraph.calibration.ml.Options (value as a Python literal), e.g.
--opt field_sigma=0.015 --opt field_tau=1.0 --opt gyro_map=True.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, print_table, rms_diff_ci  # noqa: E402
from benchmarks.peers import timed, vqf_offline, vqf_online  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402

def parse_args(argv: list[str]) -> argparse.Namespace:
    """The command line of the module docstring (--help prints it without running anything)."""
    ap = argparse.ArgumentParser(prog="broad_published.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trials", nargs="?", default=None, help="comma-separated trial numbers, e.g. 01,04 (default: all)")
    ap.add_argument("--keyframe-hz", type=float, default=None, help="Options.keyframe_hz (default: the Options default)")
    ap.add_argument("--opt", action="append", default=[], metavar="FIELD=VALUE",
                    help="any field of imugraph.calibration.ml.Options (repeatable)")
    return ap.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    kw = {} if args.keyframe_hz is None else {"keyframe_hz": args.keyframe_hz}
    options = parse_options(args.opt, **kw)
    argv = [args.trials] if args.trials else []
    select = set(argv[0].split(",")) if argv else None
    rows = []
    for num, s, mask in iter_broad(select):
        est, t_ig = timed(calibrate, s, options, allow_weak=True)
        q_off, t_off = timed(vqf_offline, s)
        q_on, _ = timed(vqf_online, s)
        score = {name: orientation_error(q, s.quat, mask, s.rate).rms_deg
                 for name, q in (("imugraph", est.quat), ("offline_vqf", q_off), ("vqf", q_on))}
        rows.append({"trial": s.name, **{k: round(v, 3) for k, v in score.items()},
                     "ratio": round(score["imugraph"] / score["offline_vqf"], 2),
                     "diff_ci95": rms_diff_ci(est.quat, q_off, s.quat, mask, s.rate),
                     "identifiable": bool(est.calibration.coverage.get("identifiable", True)),
                     "t_imugraph_s": round(t_ig, 2), "t_offline_vqf_s": round(t_off, 3)})
        if "gyro_map_select" in est.info:        # Options.gyro_map_select: the held-out test's decision
            rep = est.info["gyro_map_select"]
            rows[-1]["map_kept"] = rep.get("keep")
            rows[-1]["map_z"] = round(float(rep["z"]), 2) if "z" in rep else None
        print(rows[-1], flush=True)
    if not rows:
        print(f"broad_published: no BROAD trial matches {argv[0]!r} (expected trial numbers like 01,04; options "
              "as --opt FIELD=VALUE, --keyframe-hz HZ)", file=sys.stderr)
        return 2
    print_table(rows, list(dict.fromkeys(k for r in rows for k in r)))
    means = {k: float(np.mean([r[k] for r in rows])) for k in ("imugraph", "offline_vqf", "vqf")}
    worse = [r["trial"] for r in rows if r["imugraph"] > r["offline_vqf"]]
    clearly = [r["trial"][:2] for r in rows if r["diff_ci95"][0] > 0]
    print(f"mean RMS: imugraph {means['imugraph']:.2f}°, offline VQF {means['offline_vqf']:.2f}°, "
          f"VQF {means['vqf']:.2f}°; ratio {means['imugraph'] / means['offline_vqf']:.2f}; "
          f"trials worse than offline VQF: {len(worse)}/{len(rows)}, of them with the whole 95 % interval above 0: "
          f"{len(clearly)} ({','.join(clearly) or '-'})")
    out = Path("bench_out"); out.mkdir(exist_ok=True)
    (out / "broad_published.json").write_text(json.dumps({"rows": rows, "means": means}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
