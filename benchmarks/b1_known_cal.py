"""B1 (issue 2c): does a known-good magnetometer calibration change the error? Fit D, o and the field
direction by least squares against a reference orientation (optical `opt_quat`, or offline VQF), then run
the ML loop with θ held there (tight prior) and score.

    .venv/bin/python benchmarks/b1_known_cal.py 01,04 [opt|vqf] [--opt field=value ...]
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import imugraph.calibration.ml as ml  # noqa: E402
from benchmarks.b1_try import CACHE, compare_line, parse_opts, vqf_cached  # noqa: E402
from benchmarks.common import iter_broad  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.alignment import undelay_magnetometer  # noqa: E402
from imugraph.calibration.initial import initial_calibration  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402


def fit_field_model(y: np.ndarray, nRb: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """y_j = D·bRn_j·m + o (m unit nav-frame field): for each m a linear LS in (D, o); m by 2-D search.
    Returns D, o, dip (rad) and the RMS residual per axis."""
    ok = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(nRb.reshape(len(nRb), -1)), axis=1)
    y, bRn = y[ok], np.transpose(nRb[ok], (0, 2, 1))

    def solve(ang):
        el, az = ang
        m = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), -np.sin(el)])
        h = bRn @ m
        A = np.c_[h, np.ones(len(h))]
        X, *_ = np.linalg.lstsq(A, y, rcond=None)
        r = y - A @ X
        return float(np.mean(r ** 2)), X

    res = minimize(lambda a: solve(a)[0], x0=[np.deg2rad(69.0), 0.0], method="Nelder-Mead",
                   options={"xatol": 1e-7, "fatol": 1e-12})
    rms, X = solve(res.x)
    return X[:3].T, X[3], float(res.x[0]), float(np.sqrt(rms))


def main(argv):
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=2)
    options, argv = parse_opts(argv)
    select = set(argv[0].split(",")) if argv else None
    ref = argv[1] if len(argv) > 1 else "opt"
    if ref not in ("opt", "vqf"):
        usage_error(f"reference {ref!r}: expected opt or vqf")
    check_trials(select)
    orig = ml._theta_prior_sigma
    for num, s, mask in iter_broad(select):
        init = initial_calibration(s)
        y = undelay_magnetometer(s.t, s.mag, init.mag_delay_s) if getattr(init, "mag_delay_s", 0) else s.mag
        q_ref = s.quat if ref == "opt" else vqf_cached(num, s)
        good = np.all(np.isfinite(q_ref), axis=1)
        nRb = np.full((s.n, 3, 3), np.nan)
        nRb[good] = quat_to_rotmat(q_ref[good])
        D, o, dip, rms = fit_field_model(y, nRb)
        print(f"{num} fit vs {ref}: dip {np.rad2deg(dip):.2f} (init {np.rad2deg(init.dip_rad):.2f}) rms {rms:.3f}; "
              f"|D-D0| {np.abs(D - init.D).max():.3f} |o-o0| {np.abs(o - init.o).max():.3f}")
        init = replace(init, D=D, o=o, dip_rad=dip)
        ml._theta_prior_sigma = lambda th, tight=False: 1e-6 * orig(th, False)
        try:
            est = ml.calibrate(s, options, initial=init, allow_weak=True)
        finally:
            ml._theta_prior_sigma = orig
        qv = vqf_cached(num, s)
        print(compare_line(f"{num} fixed θ", est.quat, qv, s, mask), flush=True)
        np.save(CACHE / f"ours_{num}_known_{ref}.npy", est.quat)


if __name__ == "__main__":
    main(sys.argv[1:])
