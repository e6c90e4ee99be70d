"""Peer figures on the BROAD trials: VQF, offline VQF and ellipsoid + offline VQF, scored by
imugraph.evaluate.orientation_error (RMS over `movement`, best shift within ±3 samples, best heading).

Run: `.venv/bin/python benchmarks/peer_table.py [--no-ellipsoid]`. Reference (data README): VQF 1.76°,
offline VQF 1.02° mean over the 17 trials.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import broad_trials, load_broad_trial, peak_memory_mb, print_table  # noqa: E402
from benchmarks.peers import timed, vqf_offline, vqf_offline_ellipsoid, vqf_online  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Score the peers on every BROAD trial and print a table; returns a process exit code."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-ellipsoid", action="store_true", help="skip ellipsoid + offline VQF")
    args = ap.parse_args(argv)
    trials = broad_trials()
    if not trials:
        print("no BROAD trials found (set IMUGRAPH_DATA)")
        return 1
    peers = {"VQF": vqf_online, "offline VQF": vqf_offline}
    if not args.no_ellipsoid:
        peers["ellipsoid+offline VQF"] = vqf_offline_ellipsoid
    rows = []
    for path in trials:
        session = load_broad_trial(path)
        row: dict = {"trial": path.stem[:30]}
        for name, fn in peers.items():
            quat, sec = timed(fn, session)
            score = orientation_error(quat, session.quat, session.movement, session.rate)
            row[name] = score.rms_deg
            row[f"{name} shift"] = score.shift_samples
            row[f"{name} s"] = sec
        rows.append(row)
    cols = ["trial"] + [c for name in peers for c in (name, f"{name} shift", f"{name} s")]
    means = {c: float(np.mean([r[c] for r in rows])) for c in cols[1:]}
    print_table(rows + [{"trial": "mean", **means}], cols)
    print(f"peak memory {peak_memory_mb():.0f} MB; reference means: VQF 1.76°, offline VQF 1.02°")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
