"""C2 (issue 2c): per BROAD trial, the noise levels the ML loop settles on under Options variants — the
magnetometer residuals' correlation time τ (calibration/noise.py), the re-estimated gyro rate error κ per
round (calibration/gyro_rate.py) — with total / inclination / heading RMS (deg).

    .venv/bin/python benchmarks/c2_noise_trace.py 02,06,36 [--opt FIELD=VALUE ...]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = pop_opts(argv)
    options = parse_options(opts)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        t0 = time.process_time()
        est = calibrate(s, options, allow_weak=True)
        cpu = time.process_time() - t0
        tot, incl, head = error_parts(est.quat, s, mask)
        hist = est.info["history"]
        kappas = [round(h["gyro_rate_error"]["kappa"], 4) for h in hist if "gyro_rate_error" in h]
        lev = [round(h["gyro_rate_error"]["leverage_mean"], 3) for h in hist if "gyro_rate_error" in h]
        tau = [round(float(h.get("tau", {}).get("mag", np.nan)), 1) for h in hist]
        print(f"{num} total {tot:.3f} incl {incl:.3f} head {head:.3f} | rounds {len(hist)} cpu {cpu:.1f} s | "
              f"tau_mag {tau} used {est.info['noise_correlation']} | sigma_mag "
              f"{np.round(est.calibration.noise['mag'], 3).tolist()} | kappa {kappas} leverage {lev} "
              f"final {est.info['gyro_rate_error']:.4f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
