"""Session 19, helper D: summary of `StreamOptions.mag_delay_end` runs of benchmarks/stream_vs_batch.py against a
reference config (e.g. the session-18 default run), per trial and as means over the trials present in both.

Per trial: the stream's smoothed orientation vs the batch with d_k, heading-aligned (`vs_batch_field_h_deg`), vs the
optical truth (`stream_truth_deg`), the lags (ms: the bootstrap's, the batch's, the end graph's τ̂) and the whole-sample
shifts, and whether the ref and the option's rows are bit-identical (where the shift did not change they must be).

    .venv/bin/python benchmarks/d19_delay_summary.py --ref bench_out/s18_final_a.json,bench_out/s18_final_b.json \
        --ref-config default --new bench_out/s19_D.json,bench_out/s19_D_rest.json --new-config mag_delay_end
"""

from __future__ import annotations

import argparse
import json

import numpy as np

KEYS = ("vs_batch_field_h_deg", "stream_truth_deg", "vs_end_deg", "same_deg")


def rows(files: str, config: str) -> dict:
    """trial → row of `config` in the comma-separated JSON files (the last one wins)."""
    out = {}
    for f in files.split(","):
        for r in json.load(open(f))["rows"]:
            if r["config"] == config:
                out[r["trial"]] = r
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", required=True)
    ap.add_argument("--ref-config", default="default")
    ap.add_argument("--new", required=True)
    ap.add_argument("--new-config", default="mag_delay_end")
    a = ap.parse_args(argv)
    ref, new = rows(a.ref, a.ref_config), rows(a.new, a.new_config)
    both = sorted(set(ref) & set(new))
    print(f"{'trial':5} {'ref h':>7} {'new h':>7} {'ref tr':>7} {'new tr':>7} {'start':>6} {'batch':>6} {'end':>6} "
          f"{'shift':>6} applied identical")
    for t in both:
        r, n = ref[t], new[t]
        lag = n.get("mag_delay_ms", {})
        same = all(r[k] == n[k] for k in KEYS)
        print(f"{t:5} {r[KEYS[0]]:7.3f} {n[KEYS[0]]:7.3f} {r[KEYS[1]]:7.3f} {n[KEYS[1]]:7.3f} {lag.get('start', np.nan):6.2f} "
              f"{lag.get('batch', np.nan):6.2f} {1e3 * lag.get('tau_s', np.nan):6.2f} "
              f"{lag.get('shift_start', '-')}→{lag.get('shift_end', '-'):<3} {str(lag.get('applied')):7} {same}")
    for key in KEYS[:2]:
        a_, b_ = np.array([ref[t][key] for t in both]), np.array([new[t][key] for t in both])
        print(f"{key}: {len(both)} trials, mean {a_.mean():.3f} → {b_.mean():.3f}°, ≤ 0.1°: {(a_ <= 0.1).sum()} → "
              f"{(b_ <= 0.1).sum()}, worst change {np.max(b_ - a_):+.3f}° ({both[int(np.argmax(b_ - a_))]})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
