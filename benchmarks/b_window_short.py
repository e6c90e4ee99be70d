"""Why Options.window_trial_verdict was not the default: BROAD 34's first 19 286 samples (67 s, the stream's bootstrap
window; magnet windows 44.6–67.5 s) calibrated with the option off and on; prints per ML round the cost and which
windows are modelled, and the singular values of D and o at the end.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/b_window_short.py

Measured (session 15): off — the windows are modelled from round 2–3, D's singular values ≈ 51, 50, 49; on — the
four windows are never put on trial and left out, and the ≈ 44 s before the magnet do not identify D: it drifts to
singular values ≈ 76, 45, 4.7 while the cost falls (the coverage check judges the whole recording, before windows
are left out).

Fixed (rounds.identified_without_windows): the coverage check on the rows kept when every window is
left out (coverage.mag_spread_of_rows: 0.011 here, < MAG_MIN_SPREAD 0.05; 32 0.083, 36 0.147) sends such
windows to the σ_mag verdict (fit_offsets): on — identical to off, D's singular values 50.97, 50.30, 48.83.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial  # noqa: E402
from benchmarks._usage import no_arguments  # noqa: E402
from imugraph.calibration.ml import Options, calibrate  # noqa: E402

N_BOOT = 19286      # the stream bootstrap's samples on 34 (benchmarks/stream_speed.py --cache: n_boot)


def main() -> int:
    path = [t for t in broad_trials() if t.stem.startswith("34")][0]
    sub = load_broad_trial(path).slice(0, N_BOOT)
    for on in (False, True):
        est = calibrate(sub, Options(window_trial_verdict=on), allow_weak=True)
        c = est.calibration
        print(f"window_trial_verdict={on}: converged {c.converged}, {c.iterations} rounds, "
              f"singular values of D {np.round(np.linalg.svd(c.D)[1], 2)}, o {np.round(c.o, 2)}")
        for h in est.info["history"]:
            print(f"    cost {float(h['cost']):9.1f}  windows modelled {[w.get('modelled') for w in h.get('windows', [])]}")
    return 0


if __name__ == "__main__":
    no_arguments(__doc__)          # sys.argv: --help, or no arguments at all
    sys.exit(main())
