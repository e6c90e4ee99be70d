"""Session 22 (helper D22): the soft_tissue cases of dumped harness runs, side by side (docs/diagnose_body.md).

    .venv/bin/python benchmarks/d22_soft_cases.py d22_h16_def_s0 d22_h16_win2_s0 [...]

For every run directory (bench_out/DIR, written by `benchmarks/diagnose_body.py --dump-dir DIR`) and host: the
injected sensor, window and displacement (truth), the verdict, and the injected sensor's soft_tissue candidate
(G, its per-fold values, shrink, fitted size, fitted window, stage); then every run's confusion row counts over
all cases (none → none, X → X on the right sensor).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.output import OUT_DIR  # noqa: E402

LABELS = ("none", "soft_tissue", "gyro_bias_drift", "accelerometer_bias")


def main(argv=None) -> int:
    dirs = (argv if argv is not None else sys.argv[1:])
    for d in dirs:
        print(f"== {d}")
        right = {lab: 0 for lab in LABELS}
        n = {lab: 0 for lab in LABELS}
        for f in sorted((OUT_DIR / d).glob("*.json")):
            j = json.loads(f.read_text())
            host, label = f.stem.split("_", 2)[0] + "_" + f.stem.split("_", 2)[1], f.stem.split("_", 2)[2]
            tr, dg = j["truth"], j["diagnosis"]
            n[label] += 1
            right[label] += (dg["verdict"] == label and (label == "none" or dg["sensor"] == tr["sensor"]))
            if label == "none":                   # the clean case's best soft_tissue candidate (false-positive margin)
                e = max((x for x in dg["effects"] if x["name"] == "soft_tissue"), key=lambda x: x["loglik_gain"])
                fw = e["params"].get("window_s")
                print(f"  {host:<12} clean → {dg['verdict']}; best soft_tissue {e['sensor']} G {e['loglik_gain']:+.2f} "
                      f"folds {[round(x, 2) for x in e['loglik_gain_folds']]} shrink {e['shrink']:+.3f} size "
                      f"{1e3 * e['size']['value']:.2f} mm sig {e['significant']} rel {e['relevant']}"
                      + (f" window {fw[0]:.0f}–{fw[1]:.1f}" if fw else ""))
            if label != "soft_tissue":
                continue
            p = tr["params"]
            e = next((x for x in dg["effects"] if x["name"] == "soft_tissue" and x["sensor"] == tr["sensor"]), None)
            win = None if tr.get("t_start") is None else f"{tr['t_start']:.1f}–{tr['t_end']:.1f}"
            line = (f"  {host:<12} {tr['sensor']:<14} window {win or 'whole':<10} injected d {1e3 * p['displacement_rms_m']:.1f} mm"
                    f" → {dg['verdict']}/{dg['sensor']}")
            if e is not None:
                fw = e["params"].get("window_s")
                line += (f"; candidate G {e['loglik_gain']:+.2f} folds {[round(x, 2) for x in e['loglik_gain_folds']]}"
                         f" shrink {e['shrink']:+.3f} size {1e3 * e['size']['value']:.2f} mm stage {e['stage']}"
                         f" sig {e['significant']} rel {e['relevant']}"
                         + (f" fitted window {fw[0]:.0f}–{fw[1]:.1f}" if fw else ""))
            print(line)
        print("  correct (effect and sensor; none→none): " + ", ".join(f"{lab} {right[lab]}/{n[lab]}" for lab in LABELS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
