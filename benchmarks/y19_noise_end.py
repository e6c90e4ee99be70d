"""Session 19, helper Y: the stream's end graph re-estimates the magnetometer noise σ_m (StreamOptions.noise_end).

benchmarks/stream_vs_batch.py's comparison (its `run_trial`, every column unchanged: `vs_batch_field_h_deg` the
target, `same_deg`, `stream_truth_deg`, ...) plus, per row, the σ_m the stream's end graph used
(`StreamSmoother.noise_end_result`: start / end per axis, solves, path, thinning, CPU of the extension) next to the
bootstrap's (the stream's start) and the whole-trial batch calibration's (`full`: compared, never fed), and the
calibration.json noise the stream wrote (`end_noise_mag`).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/y19_noise_end.py TRIALS
        [--config default,noise_end] [--cache /tmp/A_cache] [--out s19_Y.json] [--feed gyr,acc,mag]
    .venv/bin/python benchmarks/y19_noise_end.py --summarise s19_Y.json[,more.json] [--config default,noise_end]
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


_FEED: dict = {}        # --feed: attribution only, the batch's σ of these channels given to the stream's start


def _recording(real):
    """stream_with_recorder that also keeps the smoother's noise_end_result, the written noise and the stream's CPU;
    with --feed the start calibration's noise of the named channels replaced by the whole-trial batch's (an
    attribution: how much of the gap the noise levels explain — never an estimator)."""
    def wrapped(s, opts, bootstrap_s, boot, n_boot):
        if _FEED:
            from dataclasses import replace
            boot = replace(boot, noise={**boot.noise, **_FEED})
        t0 = time.process_time()
        r, sm = real(s, opts, bootstrap_s, boot, n_boot)
        _LAST.append({"noise_end": getattr(sm, "noise_end_result", None),
                      "end_noise_mag": np.asarray(r.calibration.noise.get("mag"), float).tolist(),
                      "stream_cpu_s": time.process_time() - t0})
        return r, sm
    return wrapped


def _fmt(v) -> str:
    return "/".join(f"{x:.3f}" for x in v) if v is not None else "-"


def main(argv: list[str] | None = None) -> int:
    ap = stream_variant_parser(__doc__, "36,4,7,32", "default,noise_end", "s19_Y.json")
    ap.add_argument("--feed", default="", help="attribution: comma-separated channels (gyr,acc,mag) whose whole-trial "
                    "batch σ replaces the bootstrap's in the stream's start calibration (rows get config NAME+feed_CH)")
    a = ap.parse_args(argv)
    if a.summarise:
        return summarise(a.summarise.split(","), a.config.split(","))
    configs = a.config.split(",")
    paths = select_trials(a.trials)
    svb.stream_with_recorder = _recording(svb.stream_with_recorder)
    rows: list[dict] = []
    feed = [c for c in a.feed.split(",") if c]
    for p in paths:
        _LAST.clear()
        boot, _, full, _, _ = svb.calibrations(None, f"{trial_number(p):02d}", a.cache, a.bootstrap_s)
        _FEED.clear()
        _FEED.update({c: np.asarray(full.noise[c], float) for c in feed})
        new = svb.run_trial(p, configs, a.cache, a.bootstrap_s)
        for r in new if feed else ():
            r["config"] += "+feed_" + "_".join(feed)
        for r, extra in zip(new, _LAST):
            ne = extra["noise_end"] or {}
            r.update(extra, **{f"{c}_boot": np.asarray(boot.noise[c], float).tolist() for c in ("gyr", "acc", "mag")},
                     **{f"{c}_full": np.asarray(full.noise[c], float).tolist() for c in ("gyr", "acc", "mag")})
            print(stream_row_line(r, 10, f"σ_m boot {_fmt(r['mag_boot'])} end {_fmt(ne.get('sigma'))} batch "
                                         f"{_fmt(r['mag_full'])} | solves {ne.get('outer')} step "
                                         f"{ne.get('step', float('nan')):.4f} ext cpu {ne.get('cpu_s', 0.0):.1f} s"),
                  flush=True)
        rows += new
        write_json(a.out, {"rows": rows, "configs": {c: svb.CONFIGS[c] for c in configs}})
    print_run_means(rows, sorted({r["config"] for r in rows}))
    return 0


def summarise(names: list[str], configs: list[str]) -> int:
    """Per trial: each config's vs_batch_field_h / truth, σ_m boot / end / batch; per-config means over the trials
    every config has."""
    from benchmarks.common import print_config_means, rows_by_trial_config

    best = rows_by_trial_config(names, configs)
    trials = sorted({t for t, _ in best})
    for t in trials:
        cells, r0 = [], None
        for c in configs:
            r = best.get((t, c))
            if r:
                r0 = r0 or r
                ne = r.get("noise_end") or {}
                cells.append(f"{c} {r['vs_batch_field_h_deg']:.3f}/{r['stream_truth_deg']:.3f}"
                             + (f" (σ_m {_fmt(ne.get('sigma'))}, {ne.get('outer')} solves)" if ne else ""))
        print(f"{t} σ_m boot {_fmt(r0['mag_boot'])} batch {_fmt(r0['mag_full'])} | " + " | ".join(cells))
    print_config_means(best, configs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
