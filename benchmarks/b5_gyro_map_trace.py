"""B5 (issue 2c): trace the gyro scale/misalignment Ê per ML round, the gate and the error of chosen trials.

    .venv/bin/python benchmarks/b5_gyro_map_trace.py 16,06 gyro_map=True [FIELD=VALUE ...]

e.g. `16 gyro_map=True gyro_map_acc_tol=None gyro_map_min_turns=0` reproduces the runaway (Ê_xx, Ê_yy
+7 %/round) that the clean-interval mask and the gates prevent.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=())
    if not argv:
        usage_error("expected TRIALS (e.g. 16,06)")
    check_trials(set(argv[0].split(",")))
    opts = parse_options(argv[1:])
    for num, s, mask in iter_broad(set(argv[0].split(","))):
        t0 = time.perf_counter()
        est = calibrate(s, opts, allow_weak=True)
        err = orientation_error(est.quat, s.quat, mask, s.rate).rms_deg
        print(f"{num} RMS {err:.3f}°  {time.perf_counter() - t0:.1f} s  rounds {len(est.info['history'])}")
        for h in est.info["history"]:
            if "gyro_map" in h:
                E = np.array(h["gyro_map"])
                print(f"   round {h['outer']}: diag E % {np.round(100 * np.diag(E), 3)}, "
                      f"max |off-diag| % {100 * np.abs(E - np.diag(np.diag(E))).max():.3f}")
        print("   final E %", np.round(100 * est.info["gyro_map"], 3).tolist())
        gate = {k: v for k, v in est.info.get("gyro_map_gate", {}).items() if k != "E_unsettled"}
        print("   gate", gate, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
