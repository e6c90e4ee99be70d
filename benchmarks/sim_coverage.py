"""Issue 2a: over seeded simulations with known D, o, dip, bias and noise, how often do the true D and o
lie within 3 reported standard deviations, and how close are the estimated noise levels?

    .venv/bin/python benchmarks/sim_coverage.py [RUNS] [DURATION_S] [RATE_HZ]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from imugraph.calibration.ml import Options, calibrate  # noqa: E402
from imugraph.sim.scenario import distorted_session  # noqa: E402


def run(seed: int, duration: float, rate: float) -> dict:
    s, truth = distorted_session(seed, duration_s=duration, rate_hz=rate)
    cal = calibrate(s, Options()).calibration
    zD = np.abs(cal.D - truth.D) / cal.std["D"]
    zo = np.abs(cal.o - truth.o) / cal.std["o"]
    noise_err = {c: float(np.max(np.abs(np.asarray(cal.noise[c]) / np.asarray(truth.noise[c]) - 1.0)))
                 for c in ("gyr", "acc", "mag")}
    return {"seed": seed, "max_z_D": float(zD.max()), "max_z_o": float(zo.max()),
            "within_3std": bool(zD.max() <= 3 and zo.max() <= 3),
            "frac_entries_within_3std": float(np.mean(np.r_[zD.ravel(), zo] <= 3)),
            "dip_err_deg": float(cal.dip_deg - truth.dip_deg), "noise_rel_err": noise_err}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="sim_coverage.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="?", type=int, default=50, help="seeds 0..RUNS-1 (default 50)")
    ap.add_argument("duration", nargs="?", type=float, default=60.0, metavar="DURATION_S", help="s (default 60)")
    ap.add_argument("rate", nargs="?", type=float, default=100.0, metavar="RATE_HZ", help="Hz (default 100)")
    args = ap.parse_args(argv)
    runs, duration, rate = args.runs, args.duration, args.rate
    rows = []
    for seed in range(runs):
        rows.append(run(seed, duration, rate))
        r = rows[-1]
        print(f"seed {seed:3d}: max|z| D {r['max_z_D']:.2f} o {r['max_z_o']:.2f}  dip err {r['dip_err_deg']:+.3f}°  "
              f"noise rel err " + " ".join(f"{k} {v:.3f}" for k, v in r["noise_rel_err"].items()), flush=True)
    joint = np.mean([r["within_3std"] for r in rows])
    entries = np.mean([r["frac_entries_within_3std"] for r in rows])
    noise_ok = {c: float(np.mean([r["noise_rel_err"][c] <= 0.10 for r in rows])) for c in ("gyr", "acc", "mag")}
    print(f"runs {runs}: all 12 entries of D and o within 3σ in {100 * joint:.0f} % of runs; "
          f"entries within 3σ {100 * entries:.1f} %; noise within 10 %: "
          + ", ".join(f"{c} {100 * v:.0f} %" for c, v in noise_ok.items()))
    out = Path("bench_out"); out.mkdir(exist_ok=True)
    (out / "sim_coverage.json").write_text(json.dumps({"rows": rows, "joint": joint, "entries": entries,
                                                        "noise_ok": noise_ok}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
