"""The second-order (AR(2)) velocity process (Options.estimate_velocity_process "bounded_ar2"/"free_ar2",
calibration/velocity_ar2.py) on the BROAD trials: orientation error (total, inclination, heading) of the
baseline and the variant in the same run, the (a_1, a_2, q) the ML loop settles on, and — for evaluation
only, never fed to the estimate — the same parameters fitted to the optical velocities at the keyframes
(conditional least squares on the finite triples) with the normalised innovation of the estimated model
on them (≈ 1 when the model's step fits the motion).

    .venv/bin/python benchmarks/v2_velocity_ar2.py [TRIAL_NUMBERS,...] [--opt FIELD=VALUE ...]

Baseline: Options(); variant: Options() with the --opt settings (default estimate_velocity_process="free_ar2").
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts, print_variant_summary  # noqa: E402
from benchmarks.v1_velocity_process import optical_velocities  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def optical_ar2(v: np.ndarray) -> tuple[float, float, float]:
    """(a_1, a_2, q) by least squares of v_{k+1} on (v_k, v_{k−1}) over finite triples, axes pooled."""
    ok = np.all(np.isfinite(v), axis=1)
    t = ok[2:] & ok[1:-1] & ok[:-2]
    y = v[2:][t].ravel()
    X = np.stack([v[1:-1][t].ravel(), v[:-2][t].ravel()], axis=1)
    a, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(a[0]), float(a[1]), float(np.mean((y - X @ a) ** 2))


def normalised_innovation(v: np.ndarray, a1: float, a2: float, q: float) -> float:
    """RMS of (v_{k+1} − a_1 v_k − a_2 v_{k−1}) / √q over the finite triples."""
    ok = np.all(np.isfinite(v), axis=1)
    t = ok[2:] & ok[1:-1] & ok[:-2]
    r = (v[2:][t] - a1 * v[1:-1][t] - a2 * v[:-2][t]) / np.sqrt(q)
    return float(np.sqrt(np.mean(r**2)))


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    from scipy.io import loadmat

    opts, argv = pop_opts(argv)
    opts = opts or ["estimate_velocity_process='free_ar2'"]
    base, variant = parse_options([]), parse_options(opts)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    rows = []
    for num, s, mask in iter_broad(select):
        e0, e1 = calibrate(s, base, allow_weak=True), calibrate(s, variant, allow_weak=True)
        p0, p1 = error_parts(e0.quat, s, mask), error_parts(e1.quat, s, mask)
        kf = np.asarray(e1.info["keyframe_samples"])
        v_opt = optical_velocities(np.asarray(loadmat(s.source)["opt_pos"], float), kf, s.rate)
        est = next((h["velocity_ar2"] for h in reversed(e1.info["history"]) if "velocity_ar2" in h), None)
        o1, o2, oq = optical_ar2(v_opt)
        rows.append({"trial": num, "base": round(p0[0], 3), "variant": round(p1[0], 3),
                     "diff": round(p1[0] - p0[0], 3), "incl": f"{p0[1]:.3f}/{p1[1]:.3f}",
                     "head": f"{p0[2]:.3f}/{p1[2]:.3f}",
                     "ar2": None if est is None else f"{est[0]:.2f},{est[1]:.2f},{np.sqrt(est[2]):.3f}",
                     "opt_ar2": f"{o1:.2f},{o2:.2f},{np.sqrt(oq):.3f}",
                     "opt_innov": None if est is None else round(normalised_innovation(v_opt, *est), 2)})
        print(rows[-1], flush=True)
    if print_variant_summary(rows, "v2_velocity_ar2", argv[0] if argv else "", opts,
                             "  (ar2 columns: a_1, a_2, √q m/s)") is None:
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
