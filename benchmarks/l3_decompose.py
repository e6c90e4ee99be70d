"""Issue 3, task L: which parts of the batch model make the streamed smoothed orientation differ from the batch's.

The gap to close (benchmarks/stream_vs_batch.py, column `vs_batch_cal_h_deg`): the stream's smoothed orientation
(full iSAM2, StreamOptions defaults: θ a pinned graph state, so its orientation factors keep the START, i.e.
bootstrap, calibration) against `smooth_fixed` with the whole-trial batch calibration `full`. `smooth_fixed` takes
everything but the graph's form from the calibration: D, o, dip, gyro bias, gyro map E, noise levels Σω/Σa/Σm (and
their correlation times), accelerometer lead δ, the velocity process (σ_v, τ_v), the magnetometer lag and the
disturbance windows. The stream takes the same from its bootstrap calibration and adds its own model parts (the
nav-field perturbation d_k, the raw θ-state magnetometer factor, its windows' offsets Δo_w).

Per trial, RMS angle (degrees, over `movement`, after one constant heading offset: `_h`, and without) against
q_full = smooth_fixed(full):

    stream           the stream's smoothed output (the issue's number)
    same             smooth_fixed with the stream's end model (stream_vs_batch (d)): the solver part is stream − same
    ladder           same → calibrated form → no Δo_w / factor mask → no d_k (= smooth_fixed(boot)): the model part
    boot+G           smooth_fixed(boot with group G taken from full): what feeding G alone closes
    full-G           smooth_fixed(full with group G taken from boot): what G alone leaves open
    full+model       smooth_fixed(full) with the stream's model parts (d_k, raw form; no offsets): the model part
                     at the batch's calibration

Groups G (Calibration fields): Do (D, o), dip, bias (gyro_bias), gmap (gyro_map E), noise (noise levels and
coverage["noise_correlation"]), lead (acc_lead_samples), vel (velocity_sigma, velocity_tau), delay (mag_delay_s),
windows (disturbances), Dow (D, o, dip and the windows together: a modelled window's offset Δo_w is relative to
its calibration's o).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/l3_decompose.py [TRIALS] --cache DIR [--no-stream]
        [--out l3_decompose.json]

--no-stream: skip the stream (its smoothed output taken as `same`; its window offsets then none).
--ref field: every plain smooth_fixed (q_full included) with the batch model's d_k (the CLI's `smooth --calibration`
path since session 16); --ml: also the batch calibrate's own orientation (`ml_vs_ref`, `stream_vs_ml`);
--feed: also the stream itself from boot with groups from full (FEEDS: `feed_*`, oracle inputs);
--final-theta: also the stream with StreamOptions.calib_final_theta (`final_theta`); --only: no ladder / groups.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import load_broad_trial, print_table, select_trials, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.stream_vs_batch import (calibrations, rms_between, stream_offsets,  # noqa: E402
                                        stream_with_recorder, truth_err)

GROUPS = {"Do": ("D", "o"), "dip": ("dip_deg",), "bias": ("gyro_bias",), "gmap": ("gyro_map",),
          "noise": ("noise", "noise_correlation"), "lead": ("acc_lead_samples",),
          "vel": ("velocity_sigma", "velocity_tau"), "delay": ("mag_delay_s",), "windows": ("disturbances",),
          # D, o with the windows they were fitted with (a modelled window's offset is relative to its o)
          "Dow": ("D", "o", "dip_deg", "disturbances")}


def swap(base, donor, group: str):
    """`base` with the fields of `group` taken from `donor` (noise_correlation lives in coverage)."""
    kw = {}
    for f in GROUPS[group]:
        if f == "noise_correlation":
            cov = dict(base.coverage) if isinstance(base.coverage, dict) else {}
            dc = donor.coverage if isinstance(donor.coverage, dict) else {}
            cov.pop("noise_correlation", None)
            if "noise_correlation" in dc:
                cov["noise_correlation"] = dc["noise_correlation"]
            kw["coverage"] = cov
        else:
            kw[f] = getattr(donor, f)
    return replace(base, **kw)


FEEDS = {"gmap": ("gmap",), "vel": ("vel",), "Do": ("Do", "dip"), "gmap+vel": ("gmap", "vel"),
         "gmap+vel+Do": ("gmap", "vel", "Do", "dip")}


def run_trial(path: Path, cache: str | None, with_stream: bool, ref: str = "plain", ml: bool = False,
              feed: bool = False, final_theta: bool = False, bootstrap_s: float = 30.0, only: bool = False) -> dict:
    """Every comparison of the module docstring for one trial: {column: degrees, ...}."""
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.graphs.stream import StreamOptions

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    boot, n_boot, full, _, _ = calibrations(s, name, cache, bootstrap_s)
    opts = StreamOptions(lag_s=None)
    kf = opts.keyframe_hz
    field = dict(field_sigma=opts.field_sigma, field_tau=opts.field_tau)
    # both solved to convergence (target 0.1°); ref "field": every plain smooth with d_k (the CLI's `smooth
    # --calibration` path since session 16, commands/calibrate.py)
    tol = dict(keyframe_hz=kf, rotation_tol_deg=0.001, **(field if ref == "field" else {}))
    model = dict(field, mag_model="raw")
    t0 = time.process_time()
    q_full = smooth_fixed(s, full, **tol)
    one_cpu = time.process_time() - t0
    row: dict = {"trial": name, "ref": ref, "smooth_cpu_s": one_cpu}
    q_ml = None
    if ml:                       # the batch calibrate's own orientation (what `imugraph calibrate` writes)
        from imugraph.calibration.ml import Options, calibrate
        from imugraph.errors import CalibrationError
        t0 = time.process_time()
        try:
            q_ml = calibrate(s, Options()).quat
        except CalibrationError:
            q_ml = calibrate(s, Options(), allow_weak=True).quat
        row["ml_cpu_s"] = time.process_time() - t0
        row["ml_vs_ref_h"] = rms_between(q_ml, q_full, s.movement, s.rate, heading=True)

    def score(col: str, q: np.ndarray) -> None:
        row[col + "_h"] = rms_between(q, q_full, s.movement, s.rate, heading=True)
        row[col] = rms_between(q, q_full, s.movement, s.rate)

    off = None
    if with_stream:
        t0 = time.process_time()
        r, sm = stream_with_recorder(s, opts, bootstrap_s, boot, n_boot)
        row["stream_cpu_s"] = time.process_time() - t0
        score("stream", r.smoothed)
        row["stream_truth"] = truth_err(r.smoothed, s)
        if q_ml is not None:
            row["stream_vs_ml_h"] = rms_between(r.smoothed, q_ml, s.movement, s.rate, heading=True)
        off = stream_offsets(sm, sm._k + 1)
    # the model ladder from the stream's end model down to smooth_fixed(boot)
    q_same = smooth_fixed(s, boot, **{**tol, **model}, mag_offsets=off)
    score("same", q_same)
    if with_stream:
        row["stream_vs_same"] = rms_between(r.smoothed, q_same, s.movement, s.rate)
    else:
        row["stream_h"], row["stream"] = row["same_h"], row["same"]
    if not only:
        score("l_calform", smooth_fixed(s, boot, **{**tol, **model, "mag_model": "calibrated"}, mag_offsets=off))
        score("l_nooffs", smooth_fixed(s, boot, **{**tol, **model, "mag_model": "calibrated"}))
        q_boot = smooth_fixed(s, boot, **tol)
        score("boot", q_boot)
        if q_ml is not None:
            row["same_vs_ml_h"] = rms_between(q_same, q_ml, s.movement, s.rate, heading=True)
            row["boot_vs_ml_h"] = rms_between(q_boot, q_ml, s.movement, s.rate, heading=True)
        score("full+model", smooth_fixed(s, full, **{**tol, **model}))
        for g in GROUPS:
            score(f"boot+{g}", smooth_fixed(s, swap(boot, full, g), **tol))
            score(f"full-{g}", smooth_fixed(s, swap(full, boot, g), **tol))
    fed = {}
    if feed:         # the stream itself started from boot with groups taken from full (oracle feeds)
        for name_f, groups in FEEDS.items():
            cal_f = boot
            for g in groups:
                cal_f = swap(cal_f, full, g)
            fed[name_f], _ = stream_with_recorder(s, opts, bootstrap_s, cal_f, n_boot)
            score(f"feed_{name_f}", fed[name_f].smoothed)
    if final_theta:  # StreamOptions.calib_final_theta (stream_online): the end graph at the streamed θ
        same = opts.calib_final_theta        # the default since session 17: the runs above are these runs
        t0 = time.process_time()
        r_t = r if same and with_stream else stream_with_recorder(s, replace(opts, calib_final_theta=True),
                                                                  bootstrap_s, boot, n_boot)[0]
        row["final_theta_cpu_s"] = row["stream_cpu_s"] if same and with_stream else time.process_time() - t0
        score("final_theta", r_t.smoothed)
        row["final_theta_truth"] = truth_err(r_t.smoothed, s)
        if feed:
            cal_f = swap(swap(boot, full, "gmap"), full, "vel")
            r_t = fed["gmap+vel"] if same else stream_with_recorder(s, replace(opts, calib_final_theta=True),
                                                                     bootstrap_s, cal_f, n_boot)[0]
            score("final_theta_feed_gmap+vel", r_t.smoothed)
    row["full_truth"] = truth_err(q_full, s)
    row["dip_boot"], row["dip_full"] = boot.dip_deg, full.dip_deg
    return row


def main(argv: list[str] | None = None) -> int:
    """Run the trials one after the other; print the table (heading-aligned columns) and the summary."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="1,4,6,30,32,34")
    ap.add_argument("--cache", default=None, help="folder of cal_NN.pkl (benchmarks/stream_speed.py --cache)")
    ap.add_argument("--no-stream", action="store_true")
    ap.add_argument("--ref", default="plain", choices=("plain", "field"),
                    help="plain: smooth_fixed(full) as stream_vs_batch.py; field: with d_k (the CLI's smooth path)")
    ap.add_argument("--ml", action="store_true", help="also the batch calibrate's own orientation (a calibrate run)")
    ap.add_argument("--feed", action="store_true", help="also stream from boot with FEEDS' groups from full")
    ap.add_argument("--final-theta", action="store_true", help="also stream with calib_final_theta=True")
    ap.add_argument("--only", action="store_true", help="skip the smooth_fixed ladder and groups (stream rows only)")
    ap.add_argument("--out", default="l3_decompose.json")
    a = ap.parse_args(argv)
    paths = select_trials(a.trials)
    rows = []
    for p in paths:
        rows.append(run_trial(p, a.cache, not a.no_stream, a.ref, a.ml, a.feed, a.final_theta, only=a.only))
        r = rows[-1]
        print(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()), flush=True)
        write_json(a.out, {"rows": rows})
    hcols = ["stream_h", "same_h", "l_calform_h", "l_nooffs_h", "boot_h", "full+model_h"]
    hcols += ["ml_vs_ref_h", "stream_vs_ml_h", "same_vs_ml_h", "boot_vs_ml_h", "final_theta_h"]
    fcols = [f"feed_{f}_h" for f in FEEDS] + ["final_theta_feed_gmap+vel_h"]
    gcols = [f"{p}{g}_h" for p in ("boot+", "full-") for g in GROUPS]
    for cols in (hcols, fcols, gcols[:len(GROUPS)], gcols[len(GROUPS):]):
        cols = [c for c in cols if c in rows[0]]
        if cols:
            print_table(rows, ["trial"] + cols)
    for c in [c for c in hcols + fcols + gcols if c in rows[0]]:
        v = np.array([r[c] for r in rows])
        print(f"{c}: mean {v.mean():.3f}°, max {v.max():.3f}°, ≤ 0.1°: {int((v <= 0.1).sum())}/{len(v)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
