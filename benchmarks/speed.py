"""Issue 2e: speed of whole BROAD trials on one core, beside offline VQF timed in the same run.

Per trial (read once, reading not timed):
    offline VQF        benchmarks.peers.vqf_offline on the published field (the reference time)
    calibrate+smooth   imugraph.calibration.ml.calibrate(session, Options(), allow_weak=True): the ML
                       calibration, whose estimate includes the smoothed orientation (what
                       `imugraph calibrate` runs)
    smooth (known cal) imugraph.graphs.cpp_smoother.smooth_fixed(session, calibration, field_sigma, field_tau)
                       with the calibration found by the run above taken as known (what `imugraph smooth
                       --calibration` runs: with the nav-field perturbation d_k since session 15)
Each is timed --repeat times (default 1) and the fastest run is kept, wall clock (perf_counter) and CPU
(process_time); the ratio is the imugraph time over offline VQF's, each on the same trial in this process.

One core: OMP/MKL/OPENBLAS/VECLIB/NUMEXPR_NUM_THREADS are set to 1 before numpy is imported (the gtsam wheel
has no TBB, so it runs on the calling thread); the number of threads of the process after the run is
reported (Linux /proc). --pin also pins the process to one CPU (os.sched_setaffinity); not the default,
since on a shared machine a pinned process cannot escape a busy core. The load average at the start is
printed and stored, and CPU time is given beside wall time (CPU time is what contention does not inflate).
VQF is called once on a short slice before timing (its first call imports the extension).
Peak memory: the process's peak resident set (ru_maxrss) after reading and after each stage; it only
grows, so a stage's own peak is at most its figure (stages run in the order listed).

    .venv/bin/python benchmarks/speed.py [TRIALS] [--repeat R] [--pin] [--opt FIELD=VALUE ...]

TRIALS: comma-separated trial numbers; default 01 and the largest other trial file (04, 60 861 samples,
the longest of the shared trials). Targets (issue 2e): calibrate + smooth ≤ 3 s for a whole trial
(≈ 52k samples at 286 Hz), smoothing with a known calibration ≤ 1 s. Writes bench_out/speed.json.
"""

from __future__ import annotations

import os

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
               "NUMEXPR_NUM_THREADS")
for _var in THREAD_VARS:           # before numpy (and gtsam) are imported: one BLAS/OpenMP thread
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (broad_trials, load_broad_trial, parse_options, peak_memory_mb, print_table,  # noqa: E402
                               trial_number)
from benchmarks.output import write_json  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from imugraph.calibration.ml import Options, calibrate  # noqa: E402
from imugraph.graphs.cpp_smoother import smooth_fixed  # noqa: E402
import imugraph.calibration.initial  # noqa: E402,F401  (imported lazily by calibrate: not timed, like VQF's warm-up)


def pin_one_cpu() -> str:
    """Pin this process to the first CPU it may run on; returns a description."""
    if not hasattr(os, "sched_setaffinity"):
        return "not pinned (no sched_setaffinity on this platform)"
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    return f"pinned to CPU {cpu}"


def best_of(repeat: int, fn, *args, **kwargs):
    """(result of the last run, fastest wall s, CPU s of that run) over `repeat` runs."""
    best = (np.inf, np.inf)
    out = None
    for _ in range(max(1, repeat)):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn(*args, **kwargs)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        if wall < best[0]:
            best = (wall, cpu)
    return out, best[0], best[1]


def default_trials(paths: list[Path]) -> list[Path]:
    """Trial 01 and the largest other trial file (the longest recording among the shared trials)."""
    first = [p for p in paths if trial_number(p) == 1] or paths[:1]
    rest = [p for p in paths if p not in first]
    return first + ([max(rest, key=lambda p: p.stat().st_size)] if rest else [])


def thread_count() -> int | None:
    """Threads of this process now (Linux /proc/self/status), None elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Threads:"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def time_trial(path: Path, repeat: int, options: Options | None = None) -> dict:
    s = load_broad_trial(path)
    vqf_offline(s.slice(0, min(s.n, 1000)))  # warm-up: the first call imports vqf
    row: dict = {"trial": path.stem, "n": s.n, "rate_hz": s.rate, "duration_s": float(s.t[-1] - s.t[0]),
                 "mem_after_read_mb": peak_memory_mb()}
    _, row["vqf_off_s"], row["vqf_off_cpu_s"] = best_of(repeat, vqf_offline, s)
    row["mem_after_vqf_mb"] = peak_memory_mb()
    est, row["calib_smooth_s"], row["calib_smooth_cpu_s"] = best_of(repeat, calibrate, s, options or Options(),
                                                                    allow_weak=True)
    row["mem_after_calibrate_mb"] = peak_memory_mb()
    opt = options or Options()
    field = {"field_sigma": opt.field_sigma, "field_tau": opt.field_tau}      # what `imugraph smooth --calibration` runs
    _, row["smooth_known_s"], row["smooth_known_cpu_s"] = best_of(repeat, smooth_fixed, s, est.calibration, **field)
    row["mem_after_smooth_mb"] = peak_memory_mb()
    row["ratio_calib_smooth"] = row["calib_smooth_s"] / row["vqf_off_s"]
    row["ratio_smooth_known"] = row["smooth_known_s"] / row["vqf_off_s"]
    row["identifiable"] = bool(est.calibration.coverage.get("identifiable", True))
    return row


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", help="comma-separated trial numbers (default: 01 and the longest)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per stage; the fastest is kept")
    ap.add_argument("--pin", action="store_true", help="pin the process to one CPU")
    ap.add_argument("--opt", action="append", metavar="FIELD=VALUE",
                    help="set a field of imugraph.calibration.ml.Options (Python literal), repeatable")
    args = ap.parse_args(argv)
    options = parse_options(args.opt)
    paths = broad_trials()
    if args.trials:
        want = {int(x) for x in args.trials.split(",")}
        paths = [p for p in paths if trial_number(p) in want]
    else:
        paths = default_trials(paths)
    if not paths:
        print("no BROAD trial selected/found (data dir: set IMUGRAPH_DATA)")
        return 1
    pinned = pin_one_cpu() if args.pin else "not pinned"
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    env = {v: os.environ.get(v) for v in THREAD_VARS}
    print(f"one core: {', '.join(f'{k}={v}' for k, v in env.items())}; {pinned}; "
          f"load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}", flush=True)
    rows = []
    for path in paths:
        rows.append(time_trial(path, args.repeat, options))
        r = rows[-1]
        print(f"{r['trial']} ({r['n']} samples): calibrate+smooth {r['calib_smooth_s']:.2f} s "
              f"(CPU {r['calib_smooth_cpu_s']:.2f} s; {r['ratio_calib_smooth']:.0f}× offline VQF), "
              f"smooth with known calibration "
              f"{r['smooth_known_s']:.2f} s ({r['ratio_smooth_known']:.1f}×), offline VQF {r['vqf_off_s']:.3f} s; "
              f"peak memory {r['mem_after_smooth_mb']:.0f} MB", flush=True)
    cols = ["trial", "n", "vqf_off_s", "calib_smooth_s", "ratio_calib_smooth", "smooth_known_s",
            "ratio_smooth_known", "calib_smooth_cpu_s", "smooth_known_cpu_s", "mem_after_read_mb",
            "mem_after_calibrate_mb", "mem_after_smooth_mb"]
    print("\nseconds (wall, fastest of --repeat), ratio = imugraph / offline VQF, memory = process peak RSS MB")
    print_table([{**r, "trial": r["trial"][:28]} for r in rows], cols)
    summary = {"thread_env": env, "process_threads_after_run": thread_count(), "pinning": pinned,
               "load_average_start": list(load), "repeat": args.repeat,
               "target_calib_smooth_le_3s": all(r["calib_smooth_s"] <= 3.0 for r in rows),
               "target_smooth_known_le_1s": all(r["smooth_known_s"] <= 1.0 for r in rows),
               "peak_memory_mb": peak_memory_mb()}
    print(f"targets: calibrate+smooth ≤ 3 s: {summary['target_calib_smooth_le_3s']}; smooth with known "
          f"calibration ≤ 1 s: {summary['target_smooth_known_le_1s']}; "
          f"peak memory {summary['peak_memory_mb']:.0f} MB; "
          f"process threads after the run: {summary['process_threads_after_run']}")
    out = write_json("speed.json", {"rows": rows, "summary": summary})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
