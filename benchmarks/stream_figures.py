"""Issue 3's figures for the README: one BROAD trial streamed with the CLI's defaults (full iSAM2, or --lag S), its
calibration as it evolved against the whole-trial batch calibration, the filtered and smoothed orientation against
the optical reference, and the time per keyframe update.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/stream_figures.py [TRIAL] [--lag S] [--out DIR]

TRIAL: a BROAD trial number (default 01). --out: the folder of the PNGs (default docs/figures); each named
stream_NN_MODE_{calibration,orientation,timing}.png with MODE isam2 or lagS. Each panel is what `imugraph stream`
writes into its --out folder (commands/stream.write_stream_figures), plus the batch calibration
(`imugraph.calibration.ml.calibrate`, default Options) drawn dotted as the reference of the calibration panel.
Prints the numbers shown in the legends (filtered / smoothed RMS vs the reference, update p50 / p99).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial, trial_number  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trial", nargs="?", default="01")
    ap.add_argument("--lag", type=float, default=None, help="fixed lag, s (default: full iSAM2)")
    ap.add_argument("--out", default="docs/figures")
    args = ap.parse_args(argv)
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import stream_session
    from imugraph.io.stream_figures import plot_stream_calibration, plot_stream_orientation, plot_stream_timing

    paths = [p for p in broad_trials() if trial_number(p) == int(args.trial)]
    if not paths:
        print(f"stream_figures: error: TRIAL: found {args.trial}; expected a BROAD trial number present in the data")
        return 2
    s = load_broad_trial(paths[0])
    name = f"{trial_number(paths[0]):02d}"
    mode = "isam2" if args.lag is None else f"lag{args.lag:g}"
    r = stream_session(s, None, StreamOptions(lag_s=args.lag))
    batch = calibrate(s, Options(), allow_weak=True).calibration
    out = Path(args.out)
    stem = f"stream_{name}_{mode}"
    label = f"BROAD {name}, {'full iSAM2' if args.lag is None else f'fixed lag {args.lag:g} s'}"
    if r.calibration_history:
        plot_stream_calibration(out / f"{stem}_calibration.png", r.calibration_history, r.calibration, batch,
                                title=f"Calibration as streamed: {label}", reference_label="batch")
    plot_stream_orientation(out / f"{stem}_orientation.png", r.t, r.filtered, r.smoothed, s.quat, s.movement,
                            title=f"Orientation vs the optical reference: {label}")
    plot_stream_timing(out / f"{stem}_timing.png", r.update_t, r.update_ms, r.update_cpu_ms,
                       title=f"Time per keyframe update: {label}")
    f, sm = (orientation_error(q, s.quat, s.movement, s.rate).rms_deg for q in (r.filtered, r.smoothed))
    print(f"{label}: filtered {f:.2f}°, smoothed {sm:.2f}° RMS vs opt_quat; update wall p50 "
          f"{np.percentile(r.update_ms, 50):.2f} / p99 {np.percentile(r.update_ms, 99):.2f} ms, thread CPU p99 "
          f"{np.percentile(r.update_cpu_ms, 99):.2f} ms; {r.update_ms.size} updates → {out}/{stem}_*.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
