"""Issue 3, incremental runs: memory over a 30-minute simulated session through the fixed-lag stream.

A simulated 286 Hz single-IMU session (`imugraph.sim.scenario.distorted_session`: random rotations, distorted
magnetometer, gyro bias, noise) of --minutes minutes is pushed sample by sample into a `StreamSmoother` with a
fixed lag (default: stream_lag.ChainLagSmoother, 2 s) and online calibration, started from the true
calibration with the accelerometer timing δ = --acc-lead samples (default 0.5, `calibrate`'s; the stream
re-times the accelerometer by it, stream_interval.lead_interval). Every simulated minute the process's resident set size (VmRSS, /proc/self/status) is sampled.
Reported: RSS per minute, the growth per minute (least-squares slope over minutes ≥ --skip, MB/min), the
real-time factor (samples per second ÷ rate) and the update latency p50/p99.

Everything the benchmark itself holds (the session, the filtered-output array) is allocated and touched
before streaming starts, so the RSS growth is the smoother's. Two runs by default: `keep_history=False`
(filtered output only: the state a long-running acquisition loop holds) and `keep_history=True` (per-sample
rows kept for `smoothed()`: O(N) by design, ≈ 8 floats per sample).

    .venv/bin/python benchmarks/stream_memory.py [--minutes 30] [--rate 286] [--lag 2]
        [--lag-solver chain|incremental|batch] [--history both|on|off] [--skip 2] [--acc-lead 0.5]

Writes bench_out/stream_memory.json.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def rss_mb() -> float:
    """Current resident set size of this process, MB (VmRSS of /proc/self/status)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def growth_per_minute(minutes: np.ndarray, rss: np.ndarray, skip: float) -> float:
    """Least-squares slope of RSS (MB) against time (min) over minutes ≥ skip, MB/min."""
    sel = minutes >= skip
    if sel.sum() < 2:
        return float("nan")
    return float(np.polyfit(minutes[sel], rss[sel], 1)[0])


def run(session, cal, options, rate: float, skip: float) -> dict:
    """Stream the whole session; RSS sampled every simulated minute."""
    from imugraph.graphs.stream import StreamSmoother
    from imugraph.graphs.stream_run import timing_summary

    per_min = int(round(60.0 * rate))
    filtered = np.full((session.n, 4), np.nan)            # touched now: its pages are not growth
    g0 = float(np.median(np.linalg.norm(session.acc[:per_min], axis=1)))
    sm = StreamSmoother(cal, rate, options, g0=g0)
    t, gyr, acc, mag = session.t, session.gyr, session.acc, session.mag
    push = sm.push
    minutes, rss = [0.0], [rss_mb()]
    start, start_cpu = time.perf_counter(), time.process_time()
    for i in range(session.n):
        filtered[i] = push(t[i], gyr[i], acc[i], mag[i])
        if (i + 1) % per_min == 0:
            minutes.append((i + 1) / rate / 60.0)
            rss.append(rss_mb())
    sm.finish()
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
    minutes, rss = np.array(minutes), np.array(rss)
    tm = timing_summary(sm.stats.update_s, seconds, session.n, rate, sm.stats.update_cpu_s, cpu_seconds)
    err = _rms_deg(filtered, session.quat, rate)
    return {"keep_history": options.keep_history, "minutes": minutes.tolist(), "rss_mb": rss.tolist(),
            "growth_mb_per_min": growth_per_minute(minutes, rss, skip), "rss_start_mb": float(rss[0]),
            "rss_end_mb": float(rss[-1]), "realtime_factor": tm["realtime_factor"], "p50_ms": tm["p50_ms"],
            "p99_ms": tm["p99_ms"], "max_ms": tm["max_ms"], "cpu_realtime_factor": tm["cpu_realtime_factor"],
            "p50_cpu_ms": tm["p50_cpu_ms"], "p99_cpu_ms": tm["p99_cpu_ms"], "seconds": seconds, "failed": sm.stats.failed_updates,
            "filtered_deg": err, "refits": sm.stats.calib_refits}


def _rms_deg(q, ref, rate: float) -> float:
    """Filtered error against the simulated truth, ° RMS (best heading offset and time shift)."""
    from imugraph.evaluate import orientation_error
    return orientation_error(q, ref, None, rate).rms_deg


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--rate", type=float, default=286.0)
    ap.add_argument("--lag", type=float, default=2.0)
    ap.add_argument("--lag-solver", choices=("chain", "incremental", "batch"), default="chain")
    ap.add_argument("--history", choices=("both", "on", "off"), default="both")
    ap.add_argument("--skip", type=float, default=2.0, help="minutes left out of the growth fit (warm-up)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--acc-lead", type=float, default=0.5, help="δ of the calibration, samples (acc_timing)")
    a = ap.parse_args(argv)
    from imugraph.graphs.stream import StreamOptions
    from imugraph.sim.scenario import distorted_session

    start = time.perf_counter()
    session, truth = distorted_session(a.seed, a.minutes * 60.0, a.rate)
    print(f"simulated {session.n} samples ({a.minutes:g} min at {a.rate:g} Hz) in {time.perf_counter() - start:.1f} s",
          file=sys.stderr, flush=True)
    cal = replace(truth.to_calibration(), acc_lead_samples=a.acc_lead)
    rows = []
    for hist in {"both": (False, True), "on": (True,), "off": (False,)}[a.history]:
        opt = StreamOptions(lag_s=a.lag, fixed_lag_solver=a.lag_solver, keep_history=hist)
        rows.append(run(session, cal, opt, a.rate, a.skip))
        print(f"keep_history={hist} done", file=sys.stderr, flush=True)
    print_table(rows, ["keep_history", "rss_start_mb", "rss_end_mb", "growth_mb_per_min", "realtime_factor",
                       "p50_ms", "p99_ms", "max_ms", "cpu_realtime_factor", "p50_cpu_ms", "p99_cpu_ms", "failed", "filtered_deg", "refits"])
    for r in rows:
        print(f"keep_history={r['keep_history']} RSS by minute (MB): " + " ".join(f"{v:.0f}" for v in r["rss_mb"]))
    write_json("stream_memory.json", {"rows": rows, "minutes": a.minutes, "rate_hz": a.rate, "lag_s": a.lag,
                                      "lag_solver": a.lag_solver, "acc_lead_samples": a.acc_lead, "command": " ".join(sys.argv)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
