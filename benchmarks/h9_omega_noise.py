"""H9 (issue 2c), evidence only: an accelerometer-increment error growing with the rotation rate — gravity seen
through a sample-timing error δ rotates by |ω| δ, an error g |ω| δ per sample — added to the increments'
variance, Σ_e,k += Σ_j (δ g |ω_j| dt_j)² I (imugraph.factors.velocity: today σ_a² + κ_a² |a_j|²). Applied at run
time by wrapping factors.velocity.velocity_increments (helper C does not own it); the rates are the session's
gyro samples. Prints the error per trial and δ for a velocity-process mode.

    .venv/bin/python benchmarks/h9_omega_noise.py 02,07 --delays 0,0.001,0.002 [--opt FIELD=VALUE ...]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import imugraph.factors.velocity as fv  # noqa: E402
from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, floats  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402

_plain = fv.velocity_increments
STATE = {"omega": None, "delay": 0.0, "g": 9.81}


def velocity_increments(kRb, sample_kf, b_acc, dt, n_keyframes, sigma_acc, rate_error):
    dv, sig = _plain(kRb, sample_kf, b_acc, dt, n_keyframes, sigma_acc, rate_error)
    if STATE["delay"] > 0 and STATE["omega"] is not None and len(STATE["omega"]) == len(dt):
        extra = (STATE["delay"] * STATE["g"] * STATE["omega"] * dt) ** 2
        sig = np.sqrt(sig**2 + np.bincount(sample_kf, weights=extra, minlength=n_keyframes)[:-1])
    return dv, sig


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--delays"), max_args=1, values={"--delays": floats})
    opts, argv = pop_opts(argv)
    delays = [0.0, 0.001, 0.002]
    if "--delays" in argv:
        i = argv.index("--delays")
        delays = [float(x) for x in argv[i + 1].split(",")]
        argv = argv[:i] + argv[i + 2:]
    options = parse_options(opts)
    fv.velocity_increments = velocity_increments
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        STATE["omega"] = np.linalg.norm(s.gyr, axis=1)
        out = []
        for d in delays:
            STATE["delay"] = d
            t0 = time.process_time()
            est = calibrate(s, options, allow_weak=True)
            e = error_parts(est.quat, s, mask)
            out.append(f"δ {d * 1e3:.1f} ms: {e[0]:.3f} (incl {e[1]:.3f} head {e[2]:.3f}, {time.process_time() - t0:.1f} s)")
        print(f"{num}  " + "  ".join(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
