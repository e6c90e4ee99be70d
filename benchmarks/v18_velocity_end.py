"""Session 18, helper V: the stream's end-of-stream EM of the velocity process (StreamOptions.velocity_end).

benchmarks/stream_vs_batch.py's comparison (its `run_trial`, every column unchanged: `vs_batch_field_h_deg` the
target, `same_deg`, `stream_truth_deg`, ...) plus, per row, the velocity process the stream's end graph used
(`StreamSmoother.velocity_end_result`: σ̂_v, τ̂_v, outer solves, inner EM steps, CPU of the extension) next to the
bootstrap's (the stream's start) and the whole-trial batch calibration's (`full`, compared, never fed).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/v18_velocity_end.py TRIALS
        [--config default,velocity_end,velocity_end_gm] [--cache /tmp/A_cache] [--out v18_velocity_end.json]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import benchmarks.stream_vs_batch as svb  # noqa: E402
from benchmarks.common import print_run_means, select_trials, stream_row_line, stream_variant_parser, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402

_LAST: list = []


def _recording(real):
    """stream_with_recorder that also keeps the smoother's velocity_end_result and the stream's CPU time."""
    def wrapped(s, opts, bootstrap_s, boot, n_boot):
        t0 = time.process_time()
        r, sm = real(s, opts, bootstrap_s, boot, n_boot)
        _LAST.append({"velocity_end": getattr(sm, "velocity_end_result", None),
                      "stream_cpu_s": time.process_time() - t0})
        return r, sm
    return wrapped


def main(argv: list[str] | None = None) -> int:
    ap = stream_variant_parser(__doc__, "7,30,34,36", "default,velocity_end", "v18_velocity_end.json")
    a = ap.parse_args(argv)
    if a.summarise:
        return summarise(a.summarise.split(","), a.config.split(",") if a.config != ap.get_default("config") else None)
    configs = a.config.split(",")
    paths = select_trials(a.trials)
    svb.stream_with_recorder = _recording(svb.stream_with_recorder)
    rows: list[dict] = []
    for p in paths:
        _LAST.clear()
        new = svb.run_trial(p, configs, a.cache, a.bootstrap_s)
        boot, _, full, _, _ = svb.calibrations(None, f"{trial_number(p):02d}", a.cache, a.bootstrap_s)
        for r, extra in zip(new, _LAST):
            ve = extra["velocity_end"] or {}
            r.update(extra, sigma_boot=boot.velocity_sigma, tau_boot=boot.velocity_tau,
                     sigma_full=full.velocity_sigma, tau_full=full.velocity_tau,
                     sigma_end=ve.get("sigma"), tau_end=ve.get("tau"))
            print(stream_row_line(r, 16, f"σ_v boot {r['sigma_boot']:.3f} end {r['sigma_end'] or float('nan'):.3f} "
                                         f"batch {r['sigma_full']:.3f} | τ_v boot {r['tau_boot']:.3f} end "
                                         f"{r['tau_end'] or float('nan'):.3f} batch {r['tau_full']:.3f} | id "
                                         f"{ve.get('identified')} outer {ve.get('outer')} inner {ve.get('inner')} ext cpu "
                                         f"{ve.get('cpu_s', 0.0):.1f} s"), flush=True)
        rows += new
        write_json(a.out, {"rows": rows, "configs": {c: svb.CONFIGS[c] for c in configs}})
    print_run_means(rows, configs)
    return 0


def summarise(names: list[str], only: list[str] | None = None) -> int:
    """Per trial and config (the last row wins): vs_batch_field_h, truth, σ̂_v/τ̂_v vs the batch's; per-config means
    over the trials every config has."""
    from benchmarks.common import print_config_means, rows_by_trial_config

    best = rows_by_trial_config(names, only)
    configs = sorted({c for _, c in best})
    trials = sorted({t for t, _ in best})
    for t in trials:
        cells = []
        for c in configs:
            r = best.get((t, c))
            if r:
                ve = r.get("velocity_end") or {}
                cells.append(f"{c} {r['vs_batch_field_h_deg']:.3f}/{r['stream_truth_deg']:.3f}"
                             + (f" (σ {ve['sigma']:.3f} τ {ve['tau']:.3f} id {ve.get('identified')})" if ve else ""))
        r0 = next(best[(t, c)] for c in configs if (t, c) in best)
        print(f"{t} batch σ {r0['sigma_full']:.3f} τ {r0['tau_full']:.3f} | " + " | ".join(cells))
    print_config_means(best, configs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
