"""B1 (issue 2c): does a gyro scale/misalignment error explain the gap? Fit ω_true = M·ω_meas − b against a
reference orientation (relative rotations over h-sample windows, small-angle linear LS), correct the gyro
with M and run the calibration again.

    .venv/bin/python benchmarks/b1_gyro_scale.py 01,04 [opt|self] [--opt field=value ...]

opt: M from the optical reference (known-good gyro calibration); self: M from our own estimate, iterated.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.b1_try import CACHE, compare_line, parse_opts, vqf_cached  # noqa: E402
from benchmarks.common import error_parts, iter_broad  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from dataclasses import replace  # noqa: E402


def fit_gyro_map(gyr: np.ndarray, quat: np.ndarray, rate: float, h: int = 29, lag: int = 0):
    """(M, c): log(R_aᵀR_{a+h}) ≈ M·Σω dt + c·h/rate over windows with a finite reference."""
    from scipy.spatial.transform import Rotation as Rot
    good = np.all(np.isfinite(quat), 1)
    a = np.flatnonzero(good[:-h] & good[h:])
    a = a[(a + h + lag < len(gyr)) & (a + lag >= 0)]
    Ra = Rot.from_quat(np.c_[quat[a][:, 1:], quat[a][:, :1]])
    Rb = Rot.from_quat(np.c_[quat[a + h][:, 1:], quat[a + h][:, :1]])
    rel = (Ra.inv() * Rb).as_rotvec()
    cs = np.cumsum(np.r_[np.zeros((1, 3)), gyr / rate], axis=0)
    integ = cs[a + h + lag] - cs[a + lag]
    X = np.c_[integ, np.full(len(a), h / rate)]
    G, *_ = np.linalg.lstsq(X, rel, rcond=None)
    return G[:3].T, G[3]


def main(argv):
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=2)
    options, argv = parse_opts(argv)
    select = set(argv[0].split(",")) if argv else None
    mode = argv[1] if len(argv) > 1 else "opt"
    if mode not in ("opt", "self"):
        usage_error(f"reference {mode!r}: expected opt or self")
    check_trials(select)
    for num, s, mask in iter_broad(select):
        qv = vqf_cached(num, s)
        M_total = np.eye(3)
        rounds = 1 if mode == "opt" else 3
        for r in range(rounds):
            if mode == "opt":
                M, _ = fit_gyro_map(s.gyr, s.quat, s.rate, lag=1)
            else:
                est = calibrate(replace(s, gyr=s.gyr @ M_total.T), options, allow_weak=True)
                M, _ = fit_gyro_map(s.gyr @ M_total.T, est.quat, s.rate)
                o_ = list(error_parts(est.quat, s, mask))
                print(f"  {num} self round {r}: {o_[0]:.3f} (incl {o_[1]:.2f} head {o_[2]:.2f}); M diag {np.diag(M).round(4)}")
            M_total = M @ M_total
        est = calibrate(replace(s, gyr=s.gyr @ M_total.T), options, allow_weak=True)
        print(compare_line(f"{num} gyro M from {mode}", est.quat, qv, s, mask) + f"  M {M_total.round(4).tolist()}",
              flush=True)
        np.save(CACHE / f"ours_{num}_gyroM_{mode}.npy", est.quat)


if __name__ == "__main__":
    main(sys.argv[1:])
