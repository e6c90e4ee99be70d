"""Issue 3 (many sessions): `imugraph batch` on the shared BROAD trials with 1 and 2 local worker
processes, in the same run. Prints per-session time and error vs truth, the wall time of each run
(cluster start-up included), the speed-up wall(1)/wall(2), and whether both runs gave the same
results (each session's calibration.json and orientation.npz compared bit for bit, `same_outputs`;
before: only the error vs truth); writes bench_out/batch_scaling.json (results in bench_out/batch_scaling/w1, w2).

    .venv/bin/python benchmarks/batch_scaling.py [TRIAL_NUMBERS,...]          # default: all 17 trials
    .venv/bin/python benchmarks/batch_scaling.py --sim 2 --duration 30        # simulated sessions instead

BROAD trials are calibrated with allow_weak (as broad_published.py), so a trial with too little rotation
is scored rather than failed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import broad_trials, print_table  # noqa: E402
from imugraph.batch import run_batch  # noqa: E402
from imugraph.commands.calibrate import CalibrateOptions  # noqa: E402
from imugraph.io.writers import atomic_write_text  # noqa: E402

OUT = Path("bench_out")


def simulated(n: int, duration_s: float, folder: Path) -> list[Path]:
    """n simulated sessions (seeds 0..n-1, 100 Hz) written as NPZ into folder."""
    from imugraph.sim.scenario import distorted_session

    paths = []
    for seed in range(n):
        s, _ = distorted_session(seed, duration_s, 100.0)
        paths.append(folder / f"sim{seed:02d}.npz")
        np.savez(paths[-1], gyr=s.gyr, acc=s.acc, mag=s.mag, t=s.t, quat=s.quat)
    return paths


def source_digest() -> str:
    """Hash of imugraph's sources: each run's workers import the code anew, so an edit between the two
    runs would make their results differ for a reason that has nothing to do with Dask."""
    h = hashlib.sha256()
    for f in sorted((Path(__file__).resolve().parents[1] / "imugraph").rglob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def same_outputs(r1: dict, r2: dict) -> bool:
    """Both runs wrote the same results for a session: calibration.json equal as parsed JSON and the
    orientation.npz arrays equal bit for bit (failed sessions: the same error message)."""
    if r1["status"] != "ok":
        return r1.get("error") == r2.get("error")
    a, b = Path(r1["out"]), Path(r2["out"])
    if json.loads((a / "calibration.json").read_text()) != json.loads((b / "calibration.json").read_text()):
        return False
    with np.load(a / "orientation.npz") as za, np.load(b / "orientation.npz") as zb:
        return set(za.files) == set(zb.files) and all(np.array_equal(za[k], zb[k]) for k in za.files)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default=None, help="comma-separated BROAD trial numbers (01,02,...)")
    ap.add_argument("--sim", type=int, default=0, help="use N simulated sessions instead of BROAD")
    ap.add_argument("--duration", type=float, default=60.0, help="length of a simulated session, s")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="batch_scaling_"))
    try:
        if args.sim:
            paths, label = simulated(args.sim, args.duration, tmp), f"{args.sim} simulated × {args.duration:g} s"
        else:
            select = set(args.trials.split(",")) if args.trials else None
            paths = [p for p in broad_trials() if not select or p.name[:2] in select]
            label = f"{len(paths)} BROAD trials"
        if not paths:
            print("no sessions (is the shared data folder present?)", file=sys.stderr)
            return 2
        options = CalibrateOptions(allow_weak=not args.sim)
        load_before = os.getloadavg()[0]     # other work on the machine caps the possible speed-up
        runs = {}
        for workers in (1, 2):
            out = OUT / "batch_scaling" / f"w{workers}"
            start = time.perf_counter()
            digest = source_digest()
            rows = run_batch(paths, out, workers=workers, options=options, progress=True)
            runs[workers] = {"wall_s": time.perf_counter() - start, "rows": rows, "source": digest}
            if source_digest() != digest:
                print("warning: imugraph's sources changed during this run", file=sys.stderr)
            print(f"{workers} worker(s): {runs[workers]['wall_s']:.1f} s wall", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    table = []
    for r1, r2 in zip(runs[1]["rows"], runs[2]["rows"]):
        table.append({"session": r1["session"], "status": r1["status"], "t_w1_s": r1["time_s"],
                      "t_w2_s": r2["time_s"], "error_deg": r1["error_deg"],
                      "error_w2_deg": r2["error_deg"],
                      "same": r1["status"] == r2["status"] and same_outputs(r1, r2)})
    print_table(table, list(table[0].keys()))
    w1, w2 = runs[1]["wall_s"], runs[2]["wall_s"]
    work = sum(r["time_s"] or 0.0 for r in runs[1]["rows"])
    speedup = w1 / w2
    if runs[1]["source"] != runs[2]["source"]:
        print("warning: imugraph's sources changed between the two runs; results cannot be compared")
    print(f"{label}: wall 1 worker {w1:.1f} s, 2 workers {w2:.1f} s → speed-up {speedup:.2f}× "
          f"(sum of per-session times with 1 worker {work:.1f} s); "
          f"identical results in both runs: {all(r['same'] for r in table)}; "
          f"{os.cpu_count()} CPUs, load average before {load_before:.2f}, after {os.getloadavg()[0]:.2f}")
    doc = {"sessions": label, "wall_s": {"1": w1, "2": w2}, "speedup": speedup, "sum_session_s_w1": work,
           "identical": all(r["same"] for r in table),
           "same_sources": runs[1]["source"] == runs[2]["source"], "cpus": os.cpu_count(),
           "loadavg_before": load_before, "loadavg_after": os.getloadavg()[0], "rows": table}
    OUT.mkdir(exist_ok=True)
    atomic_write_text(OUT / "batch_scaling.json", json.dumps(doc, indent=1) + "\n")
    return 0 if all(r["status"] == "ok" for r in table) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
