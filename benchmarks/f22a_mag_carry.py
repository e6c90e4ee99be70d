"""Session 22, helper F22a (U22's "Also"): the lagging magnetometer's fields the stream drops at each interval's end,
and what `StreamOptions.mag_carry` (imugraph.graphs.stream_carry) does with them.

Per input, one bootstrap calibration (first --bootstrap-s seconds, as `imugraph stream`), the batch smoother of the same
model with it (`cpp_smoother.smooth_fixed`: every field row paired with its own keyframe — what the stream's smoothed
output should reproduce), then two streams from the same bootstrap: mag_carry off (the default) and on. Printed:
the field samples received and dropped (`counts`), the filtered and smoothed outputs against the batch (`*_vs_batch_deg`:
RMS angle, no heading or time alignment, as stream_speed's vs_batch) and, where the input has a reference orientation,
against it over `movement` (`*_deg`, imugraph.evaluate.orientation_error: best heading and time shift).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/f22a_mag_carry.py [INPUTS] [--lag S] [--bootstrap-s 30]
        [--same-model] [--out NAME]

INPUTS: comma-separated BROAD trial numbers and/or "fusion" (../shared/data/fusion/sensor_data.csv: a ≈ 20 Hz field of
distinct readings at 99 Hz); default "fusion". --lag: the fixed lag (chain solver); without it full iSAM2 (its end
graph pairs the carried rows with their own keyframe). Writes bench_out/f22a_mag_carry.json (--out NAME).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial, print_table, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def _inputs(spec: str) -> list:
    from imugraph.config import data_dir
    from imugraph.io.readers import load_session

    out = []
    for item in spec.split(","):
        if item == "fusion":
            out.append(("fusion", load_session(str(data_dir() / "fusion" / "sensor_data.csv"))))
        else:
            path = next((p for p in broad_trials() if trial_number(p) == int(item)), None)
            if path is None:
                raise SystemExit(f"no BROAD trial {item} in the data folder")
            out.append((f"{int(item):02d}", load_broad_trial(path)))
    return out


# --same-model: the stream's graph reduced to smooth_fixed's (calibration held, no causal windows, end extensions off)
SAME_MODEL = {"online_calibration": False, "disturb_detect": False, "windows_end": False, "velocity_end": "off",
              "gyro_map_end": False, "mag_delay_end": False}


def run(name: str, s, lag: float | None, bootstrap_s: float, same: bool = False) -> list[dict]:
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import bootstrap_calibration, stream_session

    cal, n_boot = bootstrap_calibration(s, bootstrap_s)
    extra = SAME_MODEL if same else {}
    opts = StreamOptions(lag_s=lag, **extra)
    # same model: smooth_fixed at the stream's keyframe rate and field perturbation, solved to convergence
    q_batch = smooth_fixed(s, cal, keyframe_hz=opts.keyframe_hz, field_sigma=opts.field_sigma, field_tau=opts.field_tau,
                           rotation_tol_deg=0.001) if same else smooth_fixed(s, cal)
    vs = lambda q: orientation_error(q, q_batch, None, s.rate, heading=False, max_shift=0.0).rms_deg  # noqa: E731
    truth = s.quat is not None
    rows = []
    for carry in (False, True):
        start = time.process_time()
        r = stream_session(s, None, StreamOptions(lag_s=lag, mag_carry=carry, **extra), bootstrap_s, bootstrap=(cal, n_boot))
        row = {"input": name, "model": "same" if same else "default", "mag_carry": carry, "shift": round(cal.mag_delay_s * s.rate),
               "mag_samples": r.counts["mag_samples"], "mag_dropped": r.counts["mag_dropped"],
               "filtered_vs_batch_deg": vs(r.filtered), "smoothed_vs_batch_deg": vs(r.smoothed),
               "cpu_s": time.process_time() - start}
        if truth:
            row.update(filtered_deg=orientation_error(r.filtered, s.quat, s.movement, s.rate).rms_deg,
                       smoothed_deg=orientation_error(r.smoothed, s.quat, s.movement, s.rate).rms_deg)
        rows.append(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="?", default="fusion", help='BROAD trial numbers and/or "fusion", comma separated')
    ap.add_argument("--lag", type=float, default=None, help="fixed lag, s (chain solver); default: full iSAM2")
    ap.add_argument("--bootstrap-s", type=float, default=30.0)
    ap.add_argument("--same-model", action="store_true", help="the stream reduced to smooth_fixed's model (SAME_MODEL: "
                    "bootstrap held, no causal windows, end extensions off) and smooth_fixed at its keyframe rate and "
                    "field perturbation: the carried rows should bring the stream closer to the batch")
    ap.add_argument("--out", default="f22a_mag_carry.json", help="file name under bench_out/")
    a = ap.parse_args(argv)
    rows = []
    for name, s in _inputs(a.inputs):
        rows += run(name, s, a.lag, a.bootstrap_s, a.same_model)
        print(f"{name} done", file=sys.stderr, flush=True)
    print_table(rows, ["input", "model", "mag_carry", "shift", "mag_samples", "mag_dropped", "filtered_vs_batch_deg",
                       "smoothed_vs_batch_deg", "filtered_deg", "smoothed_deg", "cpu_s"])
    write_json(a.out, {"rows": rows, "lag_s": a.lag, "bootstrap_s": a.bootstrap_s,
                                       "command": " ".join(sys.argv)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
