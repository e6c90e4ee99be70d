"""Issue 3 (incremental runs): samples that arrive late, out of order, duplicated, invalid or missing, and a
magnetometer at a lower rate than the gyro, on real BROAD trials — counted, never a crash, and what they cost.

For each trial, with the same bootstrap calibration (first 30 s), three streams through the default fixed-lag
smoother (2 s, chain solver, θ states, causal disturbance windows):

- `clean`: every sample in time order;
- `mag/4`: the magnetometer delivers every 4th sample only (NaN otherwise: no new sample);
- `arrival`: mag/4 plus a seeded mix of arrival problems — 0.5 % of samples overtaken by their successor
  (adjacent swaps), 0.5 % delivered twice, 0.1 % invalid rows (NaN gyro, extra pushes), and three network drops
  of 0.5 s whose samples never arrive.

Printed per run: the counters of `timing.json` → `counts` against what was injected, failed updates, and the
filtered and smoothed orientation error vs opt_quat over `movement` (imugraph.evaluate.orientation_error: best
constant heading and time shift) on the samples each run delivered. Writes bench_out/stream_arrival.json.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/stream_arrival.py [TRIALS] [--seed N]   # default 01,06,34
        [--kinds drop] [--drop-s S] [--gap-walk Q_W,Q_A] [--opt KEY=VALUE ...]   (--opt: StreamOptions fields)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import broad_trials, load_broad_trial, print_table, stream_overrides, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402
from imugraph.graphs.stream import StreamOptions  # noqa: E402
from imugraph.graphs.stream_run import bootstrap_calibration, session_smoother  # noqa: E402

BOOTSTRAP_S = 30.0
DROP_S = 0.5          # length of each network drop
N_DROPS = 3


def arrivals(n: int, rate: float, start: int, rng: np.random.Generator,
             kinds: frozenset = frozenset({"swap", "dup", "drop"}), drop_s: float = DROP_S) -> tuple[list[int], dict]:
    """Arrival order of sample indices ≥ start (the bootstrap's rows are streamed clean, as a device that
    buffered its first seconds), and what was injected. Swaps and duplicates are kept apart from each other and
    from the drops, so every injected event is one countable event."""
    drop_len = int(round(drop_s * rate))
    starts = np.sort(rng.choice(np.arange(start + 1000, n - 1000 - drop_len), N_DROPS, replace=False))
    dropped = set()
    for s0 in starts if "drop" in kinds else []:
        dropped.update(range(int(s0), int(s0) + drop_len))
    order = [i for i in range(n) if i not in dropped]
    k0 = next(p for p, i in enumerate(order) if i >= start)
    free = [p for p in range(k0 + 10, len(order) - 10)
            if order[p + 1] - order[p] == 1 and order[p] - order[p - 1] == 1]   # not beside a drop
    n_ev = len(order) - k0
    picks = rng.choice(free, int(0.01 * n_ev), replace=False)
    picks = np.sort(picks)
    keep, last = [], -10
    for p in picks:                               # events at least 4 positions apart
        if p - last >= 4:
            keep.append(int(p))
            last = p
    swaps = keep[0::2] if "swap" in kinds else []
    dups = set(keep[1::2]) if "dup" in kinds else set()
    for p in swaps:
        order[p], order[p + 1] = order[p + 1], order[p]
    out = []
    for p, i in enumerate(order):
        out.append(i)
        if p in dups:
            out.append(i)
    return out, {"swaps": len(swaps), "duplicates": len(dups), "dropped": len(dropped), "drops": N_DROPS if dropped else 0}


def stream(s, cal, n_boot: int, order: list[int], mag: np.ndarray, invalid_at: set[int],
           options: StreamOptions | None = None) -> dict:
    """Push the samples in `order` into a StreamSmoother (default: 2 s lag) set up as `stream_session` does."""
    sm = session_smoother(s, cal, n_boot, options or StreamOptions(lag_s=2.0))
    filtered = np.full((s.n, 4), np.nan)
    bad_gyr = [float("nan"), 0.0, 0.0]
    for j, i in enumerate(order):
        q = sm.push_floats(float(s.t[i]), *s.gyr[i].tolist(), *s.acc[i].tolist(), *mag[i].tolist())
        if np.isnan(filtered[i, 0]):
            filtered[i] = q
        if j in invalid_at:
            sm.push_floats(float(s.t[i]) + 0.5 / s.rate, *bad_gyr, *s.acc[i].tolist(), *([float("nan")] * 3))
    sm.finish()
    kept = np.searchsorted(s.t, sm.sample_times())
    smoothed = np.full((s.n, 4), np.nan)
    smoothed[kept] = sm.smoothed()
    return {"filtered": filtered, "smoothed": smoothed, "counts": sm.stats.counts()}


def score(q: np.ndarray, s) -> float:
    """RMS error over `movement` on the rows the run delivered. Rows it did not deliver are left out of the
    score and filled with their nearest earlier delivered row, so that the best-time-shift search (±3 samples,
    sub-sample steps) reads a neighbour there, not a placeholder."""
    ok = np.isfinite(q[:, 0])
    idx = np.maximum.accumulate(np.where(ok, np.arange(len(q)), 0))
    idx[:np.argmax(ok)] = np.argmax(ok)                        # rows before the first delivered one
    return orientation_error(q[idx], s.quat, s.movement & ok, s.rate).rms_deg


def run_trial(path: Path, seed: int, kinds: frozenset, drop_s: float = DROP_S, gap_walk: tuple | None = None,
              overrides: dict | None = None) -> list[dict]:
    """overrides: StreamOptions fields set in every run (--opt; the 2 s lag unless lag_s is among them)."""
    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    cal, n_boot = bootstrap_calibration(s, BOOTSTRAP_S)
    rng = np.random.default_rng(seed)
    mag4 = s.mag.copy()
    mag4[np.arange(s.n) % 4 != 0] = np.nan
    order, injected = arrivals(s.n, s.rate, n_boot, rng, kinds, drop_s)
    invalid_at = set(int(j) for j in rng.choice(np.arange(n_boot, len(order)), int(0.001 * (len(order) - n_boot)),
                                                replace=False)) if "invalid" in kinds else set()
    injected["invalid"] = len(invalid_at)
    runs = [("clean", list(range(s.n)), s.mag, set()), ("mag/4", list(range(s.n)), mag4, set()),
            ("arrival", order, mag4, invalid_at)]
    rows = []
    for label, ordr, mag, inv in runs:
        extra = dict(overrides or {})
        if gap_walk is not None:
            extra.update(gap_rate_walk=gap_walk[0], gap_acc_walk=gap_walk[1])
        opts = StreamOptions(**{"lag_s": 2.0, **extra}) if extra else None
        r = stream(s, cal, n_boot, ordr, mag, inv, opts)
        c = r["counts"]
        rows.append({"trial": name, "run": label, "filtered_deg": score(r["filtered"], s),
                     "smoothed_deg": score(r["smoothed"], s), "failed": c.get("failed_updates", 0),
                     "dup": c.get("duplicates"), "late_ins": c.get("late_inserted"), "late_drop": c.get("late_dropped"),
                     "invalid": c.get("invalid"), "gaps": c.get("gaps"), "missing": c.get("missing"),
                     "mag_samples": c.get("mag_samples"),
                     "injected": "" if label != "arrival" else
                     f"swap {injected['swaps']} dup {injected['duplicates']} inv {injected['invalid']} "
                     f"drop {injected['drops']}×{int(round(drop_s * s.rate))}"})
        print(f"trial {name} {label} done", file=sys.stderr, flush=True)
    return rows


def drop_arguments(doc: str) -> argparse.ArgumentParser:
    """The arguments this benchmark shares with batch_gaps.py: trials, --seed, --drop-s."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("trials", nargs="?", default="01,06,34", help="BROAD trial numbers, comma separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drop-s", type=float, default=DROP_S, help="length of each of the three drops, s")
    return ap


def trial_paths(trials: str) -> list[Path]:
    """The BROAD trials named (e.g. "01,06,34"), with a message on stderr when none is in the data folder."""
    want = {int(x) for x in trials.split(",")}
    paths = [p for p in broad_trials() if trial_number(p) in want]
    if not paths:
        print(f"no BROAD trial {trials} in the data folder", file=sys.stderr)
    return paths


def main(argv=None) -> int:
    ap = drop_arguments(__doc__)
    ap.add_argument("--gap-walk", default=None, metavar="Q_W,Q_A",
                    help="the stream's gap densities q_ω (rad/s^1.5), q_a (m/s^2.5) (default: factors.gaps'; 0,0: "
                         "missing time trusted like measured time)")
    ap.add_argument("--kinds", default="swap,dup,invalid,drop",
                    help="arrival problems injected in the `arrival` run (comma separated subset)")
    ap.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                    help="StreamOptions field=value (Python literal), repeatable; e.g. position_sigma=0.3")
    a = ap.parse_args(argv)
    overrides = stream_overrides(a.opt)
    paths = trial_paths(a.trials)
    if not paths:
        return 2
    rows = [row for p in paths for row in run_trial(p, a.seed, frozenset(a.kinds.split(",")), a.drop_s,
                                                        None if a.gap_walk is None else
                                                        tuple(float(x) for x in a.gap_walk.split(",")), overrides)]
    cols = ["trial", "run", "filtered_deg", "smoothed_deg", "failed", "dup", "late_ins", "late_drop", "invalid",
            "gaps", "missing", "mag_samples", "injected"]
    print_table(rows, cols)
    write_json("stream_arrival.json", {"seed": a.seed, "drop_s": a.drop_s, "kinds": a.kinds, "gap_walk": a.gap_walk,
                                       "opt": a.opt, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
