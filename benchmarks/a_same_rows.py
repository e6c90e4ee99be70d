"""Issue 3, task A: which magnetometer rows the stream's end graph holds, against `smooth_fixed` of the same model.

A lagging magnetometer (Calibration.mag_delay_s, n = round(τ·rate) samples; BROAD: 3 at 286 Hz) reports the field of
row i with sample i + n. The stream attaches it there (`stream_interval.ArrivalMixin._attach_delayed_mag`) while the
interval is open; the fields of an interval's last n rows arrive with the next interval's first n samples, after the
interval has closed, and are dropped (`counts.mag_dropped`). The batch's `Calibration.corrected` (undelay_magnetometer)
keeps every row. So the stream's magnetometer factor of keyframe k averages n fewer rows than the reference's.

Per trial: the stream (default StreamOptions, full iSAM2, as benchmarks/stream_vs_batch.py) once, then the same-model
reference (stream_vs_batch.same_model: start calibration, d_k, raw factor form, the stream's window offsets) on
    all rows          the session as recorded (`same_deg` of stream_vs_batch)
    stream's rows     the raw field rows the stream dropped set to NaN: raw rows kf_j … kf_j + n − 1 of every keyframe
                      j ≥ 1 (after undelay they are interval j − 1's last n rows)
and the RMS angle between the stream's smoothed orientation and each (over `movement`, no alignment). With
--stream-opt KEY=VALUE the stream runs with that StreamOptions field changed (e.g. mag_carry=True).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/a_same_rows.py 30 [--cache DIR] [--stream-opt KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial, print_table, trial_number  # noqa: E402
from benchmarks.stream_vs_batch import (calibrations, rms_between, same_model, stream_with_recorder,  # noqa: E402
                                        truth_err)


def stream_rows_only(s, stride: int, shift: int):
    """The session with the raw field rows the stream cannot use set to NaN (module docstring)."""
    from imugraph.factors.gyro import keyframe_layout

    kf, _ = keyframe_layout(s.n, stride, s.dt)
    mag = np.array(s.mag, float)
    for j in kf[1:-1]:                      # the last keyframe has no interval after it
        mag[j:j + shift] = np.nan
    return replace(s, mag=mag)


def run_trial(path: Path, cache: str | None, extra: dict) -> dict:
    from imugraph.graphs.stream import StreamOptions

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    boot, n_boot, _, _, _ = calibrations(s, name, cache, 30.0)
    opts = StreamOptions(lag_s=None, **extra)
    r, sm = stream_with_recorder(s, opts, 30.0, boot, n_boot)
    kf_hz = opts.keyframe_hz
    same_all = same_model(s, opts, r, sm, boot, kf_hz)
    shift = int(round(boot.mag_delay_s * s.rate))
    s_rows = stream_rows_only(s, sm.stride, shift) if shift > 0 else s
    same_rows = same_model(s_rows, opts, r, sm, boot, kf_hz)
    row = {"trial": name, "shift": shift, "mag_dropped": r.counts.get("mag_dropped"),
           "window_keyframes": same_all["window_keyframes"], "stream_truth_deg": truth_err(r.smoothed, s)}
    for label, same in (("all", same_all), ("rows", same_rows)):
        q = same["q"]
        row[f"same_{label}_deg"] = rms_between(r.smoothed, q["same"], s.movement, s.rate)
        row[f"nooffs_{label}_deg"] = rms_between(r.smoothed, q["same_nooffs"], s.movement, s.rate)
        row[f"ref_truth_{label}_deg"] = truth_err(q["same"], s)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="30")
    ap.add_argument("--cache", default=None, help="folder of cal_NN.pkl (stream_vs_batch.py / stream_speed.py)")
    ap.add_argument("--stream-opt", action="append", default=[], help="KEY=VALUE: a StreamOptions field")
    a = ap.parse_args(argv)
    extra = {k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.stream_opt)}
    every = a.trials == "all"
    wanted = set() if every else {int(x) for x in a.trials.split(",")}
    rows = []
    for p in broad_trials():
        if every or trial_number(p) in wanted:
            rows.append(run_trial(p, a.cache, extra))
            print(f"trial {rows[-1]['trial']} done", file=sys.stderr, flush=True)
    print_table(rows, list(rows[0]))
    for k in ("same_all_deg", "same_rows_deg"):
        v = np.array([r[k] for r in rows])
        print(f"{k}: mean {v.mean():.3f}°, max {v.max():.3f}°, ≤ 0.1°: {int((v <= 0.1).sum())}/{len(v)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
