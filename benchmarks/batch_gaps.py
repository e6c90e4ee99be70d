"""Issue 2/3: batch calibration + smoothing (`imugraph calibrate`) of BROAD trials with samples that never
arrived — the held-sample gap model (imugraph.factors.gaps) against trusting the missing time like measured time.

Per trial: the clean recording, then the same recording with N_DROPS drops of DROP_S seconds removed (seeded
positions after the first 30 s, as benchmarks/stream_arrival.py), each calibrated and smoothed from scratch
(allow_weak, as broad_published.py); with `--ablate`, a third run with the gap model switched off (no gap
variance, no keyframe at a gap, the old per-sample blend). Scored against opt_quat over `movement` on the
samples each run has (imugraph.evaluate.orientation_error: best constant heading and time shift). `q_emp`: the
recording's own rate-walk density at 0.25 s (the model's fixed q_ω is 3 rad/s^1.5).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/batch_gaps.py [TRIALS] [--ablate] [--seed N]   # default 01,06,34
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import load_broad_trial, print_table, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.stream_arrival import DROP_S, N_DROPS, arrivals, drop_arguments, trial_paths  # noqa: E402
from benchmarks.stream_arrival import score as arrival_score  # noqa: E402
from imugraph.calibration.ml import Options, calibrate  # noqa: E402

START_S = 30.0     # drops only after the first 30 s (as the stream benchmark's bootstrap window)


def dropped(s, seed: int, drop_s: float = DROP_S):
    """The session without N_DROPS seeded runs of DROP_S s (arrival order from stream_arrival, drops only)."""
    start = int(np.searchsorted(s.t, s.t[0] + START_S))
    order, _ = arrivals(s.n, s.rate, start, np.random.default_rng(seed), frozenset({"drop"}), drop_s)
    keep = np.zeros(s.n, bool)
    keep[order] = True
    return dataclasses.replace(s, t=s.t[keep], gyr=s.gyr[keep], acc=s.acc[keep], mag=s.mag[keep],
                               quat=s.quat[keep], movement=s.movement[keep]), int((~keep).sum())


def score(s, session, gap_model: bool = True) -> float:
    est = calibrate(session, Options(gap_model=gap_model), allow_weak=True)
    q = np.full((s.n, 4), np.nan)
    q[np.searchsorted(s.t, est.t)] = est.quat
    return arrival_score(q, s)


def empirical_rate_walk(s, h: float = 0.25) -> float:
    """The recording's own q_ω: the rate held over h seconds is off by e = ∫₀^h ω dt − ω(0) h; for a random walk
    of density q, E[e²] = q² h³ / 3 per axis (gaps eq. G1), so q̂ = √(3 mean(e²) / h³) over every start sample."""
    T = 1.0 / s.rate
    m = int(round(h / T))
    integral = np.vstack([np.zeros(3), np.cumsum(s.gyr * T, axis=0)])
    e = integral[m:] - integral[:-m] - s.gyr[:len(integral) - m] * (m * T)
    return float(np.sqrt(3.0 * np.mean(e**2) / (m * T) ** 3))


def main(argv=None) -> int:
    ap = drop_arguments(__doc__)
    ap.add_argument("--ablate", action="store_true", help="also run with Options(gap_model=False)")
    a = ap.parse_args(argv)
    paths = trial_paths(a.trials)
    if not paths:
        return 2
    rows = []
    for p in paths:
        s = load_broad_trial(p)
        gapped, n_missing = dropped(s, a.seed, a.drop_s)
        rows.append({"trial": f"{trial_number(p):02d}", "missing": n_missing, "clean_deg": score(s, s),
                     "drops_deg": score(s, gapped), "q_emp": empirical_rate_walk(s)})
        print(f"trial {trial_number(p):02d} done", file=sys.stderr, flush=True)
    if a.ablate:                                   # Options(gap_model=False): the behaviour before session 16
        for row, p in zip(rows, paths):
            s = load_broad_trial(p)
            row["drops_no_gap_model_deg"] = score(s, dropped(s, a.seed, a.drop_s)[0], gap_model=False)
    cols = ["trial", "missing", "clean_deg", "drops_deg"] + (["drops_no_gap_model_deg"] if a.ablate else []) + ["q_emp"]
    print_table(rows, cols)
    print(f"{N_DROPS} drops of {a.drop_s:g} s per trial, seed {a.seed}")
    write_json("batch_gaps.json", {"seed": a.seed, "drop_s": a.drop_s, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
