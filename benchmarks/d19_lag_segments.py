"""Session 19, helper D: is the magnetometer lag of a BROAD trial one constant, and which whole-sample shift does the
optical truth prefer? (the evidence behind StreamOptions.mag_delay_end; docs/stream.md "Session 19, helper D").

Per trial, with the whole-trial batch calibration (from --cache, cal_NN.pkl as benchmarks/stream_vs_batch.py writes):
    lag_whole_ms     calibration.alignment.estimate_mag_delay on the whole trial: the raw field calibrated with the batch's
                     D, o (m̃ = D⁻¹(y − o)), the gyro minus the batch's bias (as calibration.initial, but at the final θ)
    lag_seg_ms       the same on consecutive SEG-second segments (NaN: no clear optimum)
    lag_holes_ms     lag_whole_ms without the rows a stream at the bootstrap's shift s0 drops (stream_delay_end)
    lag_filled_ms    lag_holes_ms with those holes filled by linear interpolation (stream_delay_end.fill_short_holes)
    lag_bootcal_ms   lag_whole_ms with m̃ calibrated by the bootstrap's D, o
    truth_shift_N    RMS error vs the optical truth of smooth_fixed (the batch path, `smooth --calibration`: with the
                     batch model's d_k, the stream's keyframe rate) with the batch calibration and mag_delay_s = N/rate,
                     N = 1 … 4 (the lag's whole-sample shift; undelay_magnetometer)

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/d19_lag_segments.py 12,26,32,34 --cache /tmp/A_cache [--seg 30]
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import load_broad_trial, select_trials, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def main(argv=None) -> int:
    from imugraph.calibration.alignment import estimate_mag_delay
    from imugraph.calibration.ml import Options
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.graphs.stream import StreamOptions

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials")
    ap.add_argument("--cache", required=True)
    ap.add_argument("--seg", type=float, default=30.0)
    ap.add_argument("--out", default="d19_lag_segments.json")
    a = ap.parse_args(argv)
    rows = []
    for path in select_trials(a.trials):
        s = load_broad_trial(path)
        name = f"{trial_number(path):02d}"
        cached = pickle.loads((Path(a.cache) / f"cal_{name}.pkl").read_bytes())
        full, boot = cached["full"], cached["boot"]
        m = full.apply(s.mag)
        w = np.asarray(s.gyr, float) - np.asarray(full.gyro_bias, float)
        whole = 1e3 * estimate_mag_delay(s.t, m, w)
        # attribution of the stream's τ̂: the same with the rows a stream of shift s0 drops (each 0.1 s interval's last
        # s0 rows on the stream's pairing = arrival rows s0 … 2 s0 − 1 after each keyframe), and with the bootstrap's D, o
        s0, stride = int(round(boot.mag_delay_s * s.rate)), int(round(s.rate / StreamOptions().keyframe_hz))
        held = np.arange(s.n) - s0
        m_holes = np.where(((held >= 0) & (held % stride >= stride - s0))[:, None], np.nan, m)
        holes = 1e3 * estimate_mag_delay(s.t, m_holes, w)
        from imugraph.graphs.stream_delay_end import fill_short_holes
        filled = 1e3 * estimate_mag_delay(s.t, fill_short_holes(s.t, m_holes, s0), w)
        startcal = 1e3 * estimate_mag_delay(s.t, boot.apply(s.mag), w)
        segs = []
        edges = np.arange(s.t[0], s.t[-1], a.seg)
        for t0 in edges:
            sel = (s.t >= t0) & (s.t < t0 + a.seg)
            if sel.sum() < a.seg * s.rate * 0.5:
                continue
            tau = estimate_mag_delay(s.t[sel], m[sel], w[sel])
            segs.append(round(1e3 * tau, 2) if tau != 0.0 else float("nan"))
        row = {"trial": name, "rate": s.rate, "lag_batch_ms": 1e3 * full.mag_delay_s, "lag_whole_ms": whole,
               "lag_seg_ms": segs, "lag_holes_ms": holes, "lag_filled_ms": filled, "lag_bootcal_ms": startcal}
        kf = StreamOptions().keyframe_hz
        for n in (1, 2, 3, 4):
            q = smooth_fixed(s, replace(full, mag_delay_s=n / s.rate), keyframe_hz=kf, field_sigma=Options().field_sigma,
                             field_tau=Options().field_tau)
            row[f"truth_shift_{n}"] = orientation_error(q, s.quat, s.movement, s.rate).rms_deg
        rows.append(row)
        print(f"{name}: batch {row['lag_batch_ms']:.2f} ms, whole {whole:.2f} ms (shift {whole * s.rate / 1e3:.2f}), "
              f"with the stream's holes {holes:.2f} (filled {filled:.2f}), with the bootstrap's D, o {startcal:.2f}; "
              f"per {a.seg:.0f} s: {segs}; vs truth by shift 1/2/3/4: "
              + " / ".join(f"{row[f'truth_shift_{n}']:.3f}" for n in (1, 2, 3, 4)), flush=True)
        write_json(a.out, {"rows": rows, "argv": sys.argv[1:]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
