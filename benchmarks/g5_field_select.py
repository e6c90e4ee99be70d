"""G5 (issue 2c): the field process (σ_d, τ_d) chosen per BROAD trial by held-out magnetometer prediction
(imugraph.calibration.field_select; Options.field_select), against the defaults and offline VQF.

For each trial: the held-out score of every candidate (lower is better; the truth is not used), the one chosen,
and the RMS orientation error over `movement` (scored as benchmarks/broad_published.py does: opt_quat scores,
it sets nothing) of the default run, the chosen run, and — for information only — every candidate's full run
(--all); per candidate: [1e4 × score, paired z against the first, its full-run error]. `--map` adds the candidates with the gyro map off (idea 2: is the gyro map borne out by held-out data?); `--map-only`: just
the gyro map on against off.

    .venv/bin/python benchmarks/g5_field_select.py [TRIALS] [--all] [--map | --map-only] [--block S] [--folds F] [--opt F=V ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration import field_select as fs  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402


def _flag(argv, name, default=None, cast=float):
    if name in argv:
        i = argv.index(name)
        return cast(argv[i + 1]), argv[:i] + argv[i + 2:]
    return default, argv


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--block", "--folds"), switches=("--all", "--map", "--map-only"),
                 max_args=1, values={"--block": float, "--folds": int})
    opts, argv = pop_opts(argv)
    options = parse_options(opts)
    full_all = "--all" in argv
    with_map = "--map" in argv
    map_only = "--map-only" in argv
    argv = [a for a in argv if a not in ("--all", "--map", "--map-only")]
    block, argv = _flag(argv, "--block", options.field_select_block_s)
    folds, argv = _flag(argv, "--folds", options.field_select_folds, int)
    cands = list(fs.DEFAULT_CANDIDATES)
    if with_map:
        cands += [fs.Candidate(gyro_map=False)]
    if map_only:                       # only: the gyro map on (the options' setting) against off
        cands = [fs.Candidate(), fs.Candidate(gyro_map=False)]
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    rows = []
    for num, s, mask in iter_broad(select):
        err = lambda q: orientation_error(q, s.quat, mask, s.rate).rms_deg   # noqa: E731
        t0 = time.process_time()
        best, table, init = fs.select(s, options, cands, block, folds, allow_weak=True)
        t_sel = time.process_time() - t0
        full = {}
        for r in table:
            c = r["candidate"]
            if full_all or c == best or c == fs.Candidate():
                full[c] = err(calibrate(s, c.apply(options), initial=init, allow_weak=True).quat)
        row = {"trial": num, "offline_vqf": round(err(vqf_offline(s)), 3),
               "default": round(full[fs.Candidate()], 3), "chosen": best.label(),
               "selected": round(full[best], 3), "select_cpu_s": round(t_sel, 1),
               "scores": {r["candidate"].label(): [round(1e4 * r["score"], 3), round(r.get("z", np.nan), 2),
                                                  round(full.get(r["candidate"], np.nan), 3)]
                          for r in table}}
        rows.append(row)
        print(json.dumps(row, ensure_ascii=False), flush=True)
    if not rows:
        print(f"g5_field_select: no BROAD trial matches {sorted(select or [])}", file=sys.stderr)
        return 2
    for key in ("offline_vqf", "default", "selected"):
        print(f"mean {key}: {np.mean([r[key] for r in rows]):.3f}°")
    print("behind offline VQF: default", [r["trial"] for r in rows if r["default"] > r["offline_vqf"]],
          "selected", [r["trial"] for r in rows if r["selected"] > r["offline_vqf"]])
    out = Path("bench_out"); out.mkdir(exist_ok=True)
    (out / "g5_field_select.json").write_text(json.dumps(rows, indent=1, ensure_ascii=False))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
