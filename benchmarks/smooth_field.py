"""`imugraph smooth --calibration FILE` (cpp_smoother.smooth_fixed) with and without the nav-field perturbation d_k
(`field_sigma`, imugraph.graphs.cpp_field) on the BROAD trials, given each trial's whole-trial batch calibration.

Per trial: RMS error against the optical truth over `movement` (best heading offset and time shift, as every BROAD
score: imugraph.evaluate.orientation_error) and the CPU time of each smooth (time.process_time, the load of a shared
machine does not inflate it much; the wall time is printed too), for
    plain      smooth_fixed(s, cal, keyframe_hz)                                  (`smooth --calibration --no-field`)
    field      + field_sigma=(0.015, 0.003, 0.015), field_tau=1 s                  (calibration.ml.Options' defaults)
    field_raw  + mag_model="raw" (the stream's θ-state factor form)
Calibrations: --cache DIR with cal_NN.pkl ("full": benchmarks/stream_vs_batch.py --cache writes them), else
`calibrate(s, Options())` here (allow_weak where the data do not identify it).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/smooth_field.py [TRIALS|all] [--cache DIR] [--keyframe-hz 5]
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import load_broad_trial, print_table, select_trials, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from imugraph.calibration.options import Options  # noqa: E402

FIELD = {"field_sigma": Options().field_sigma, "field_tau": Options().field_tau}   # what the CLI passes
CONFIGS = {"plain": {}, "field": FIELD, "field_raw": {**FIELD, "mag_model": "raw"}}


def batch_calibration(s, name: str, cache: str | None):
    p = Path(cache) / f"cal_{name}.pkl" if cache else None
    if p is not None and p.exists():
        c = pickle.loads(p.read_bytes())
        if "full" in c:
            return c["full"]
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.errors import CalibrationError
    try:
        return calibrate(s, Options()).calibration
    except CalibrationError:
        return calibrate(s, Options(), allow_weak=True).calibration


def main(argv: list[str] | None = None) -> int:
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.cpp_smoother import smooth_fixed

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="all")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--keyframe-hz", type=float, default=5.0)
    ap.add_argument("--out", default="smooth_field.json")
    a = ap.parse_args(argv)
    paths = select_trials(a.trials)
    rows = []
    for p in paths:
        s = load_broad_trial(p)
        name = f"{trial_number(p):02d}"
        cal = batch_calibration(s, name, a.cache)
        row = {"trial": name, "samples": s.n}
        for cfg, kw in CONFIGS.items():
            t0, c0 = time.perf_counter(), time.process_time()
            q = smooth_fixed(s, cal, keyframe_hz=a.keyframe_hz, **kw)
            row[f"{cfg}_cpu_s"], row[f"{cfg}_wall_s"] = time.process_time() - c0, time.perf_counter() - t0
            row[f"{cfg}_deg"] = orientation_error(q, s.quat, s.movement, s.rate).rms_deg
        rows.append(row)
        print(" ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), flush=True)
        write_json(a.out, {"rows": rows, "configs": CONFIGS, "keyframe_hz": a.keyframe_hz})
    cols = ["trial"] + [f"{c}_{x}" for c in CONFIGS for x in ("deg", "cpu_s")]
    print_table(rows, cols)
    for c in CONFIGS:
        e, t = np.array([r[f"{c}_deg"] for r in rows]), np.array([r[f"{c}_cpu_s"] for r in rows])
        print(f"{c}: mean {e.mean():.3f}° (max {e.max():.3f}°), CPU mean {t.mean():.2f} s, max {t.max():.2f} s")
    if rows:
        d = np.array([r["field_deg"] - r["plain_deg"] for r in rows])
        print(f"field − plain: mean {d.mean():+.3f}°, better on {int((d < 0).sum())}/{len(d)}, worst {d.max():+.3f}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
