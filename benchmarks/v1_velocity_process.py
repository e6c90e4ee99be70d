"""The velocity process's parameters estimated in the ML loop (Options.estimate_velocity_process) on the
BROAD trials: orientation error of today's defaults and of the variant in the same run, the (σ_v, τ_v) the
ML loop settles on, and — for evaluation only, never fed to the estimate — the same two parameters
measured on the optical velocities (opt_pos differentiated at the keyframes) and the normalised residual
of each model's Gauss–Markov step against them (≈ 1 when the model's step size fits the motion).

    .venv/bin/python benchmarks/v1_velocity_process.py [TRIAL_NUMBERS,...] [--opt FIELD=VALUE ...] [--base-opt F=V ...]

--opt sets the variant's Options (default: estimate_velocity_process="bounded"); the baseline is Options()
with the `--base-opt FIELD=VALUE` settings, which the variant also gets.
Writes bench_out/v1_velocity_process.json.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts, print_variant_summary  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402
from imugraph.factors.velocity import gauss_markov_axes  # noqa: E402

HALF_WINDOW_S = 0.05     # central difference of the optical position over ±this, s
DEFAULT_VARIANT = ["estimate_velocity_process='bounded'"]


def optical_velocities(pos: np.ndarray, kf: np.ndarray, rate: float) -> np.ndarray:
    """(K, 3) optical velocities at the keyframe samples, m/s (NaN where tracking dropped)."""
    h = max(1, int(round(HALF_WINDOW_S * rate)))
    lo, hi = np.clip(kf - h, 0, len(pos) - 1), np.clip(kf + h, 0, len(pos) - 1)
    return (pos[hi] - pos[lo]) / ((hi - lo)[:, None] / rate)


def optical_process(v: np.ndarray, dt: float) -> tuple[float, float]:
    """Moment estimates on the finite keyframe pairs: σ² = mean |v|²/3, φ = Σ v_k·v_{k+1} / Σ |v_k|²."""
    ok = np.all(np.isfinite(v), axis=1)
    pair = ok[:-1] & ok[1:]
    phi = np.sum(v[:-1][pair] * v[1:][pair]) / np.sum(v[:-1][pair] ** 2)
    return float(np.sqrt(np.mean(v[ok] ** 2))), float(-dt / np.log(np.clip(phi, 1e-6, 1 - 1e-9)))


def normalised_step(v: np.ndarray, dt: float, sigma, tau) -> float:
    """RMS of the whitened Gauss–Markov step (v_{k+1} − φ v_k)/σ_w over the finite pairs, per component
    (σ, τ scalars or per nav axis; the optical frame is ENU, z up like the nav frame)."""
    ok = np.all(np.isfinite(v), axis=1)
    pair = ok[:-1] & ok[1:]
    phi, sig_w = gauss_markov_axes(np.array([dt]), sigma, tau)
    r = (v[1:][pair] - phi * v[:-1][pair]) / sig_w
    return float(np.sqrt(np.mean(r**2)))


def _r(x: np.ndarray):
    """A scalar or a per-axis array, rounded for the table (per axis: horizontal/vertical when they differ)."""
    x = np.round(np.asarray(x, float), 3)
    return float(x) if x.ndim == 0 else (f"{x[0]}/{x[2]}" if x[0] == x[1] else x.tolist())


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--base-opt"), max_args=1)
    from scipy.io import loadmat

    base_opts, argv = pop_opts([("--opt" if a == "--base-opt" else "--keep" if a == "--opt" else a) for a in argv])
    argv = [("--opt" if a == "--keep" else a) for a in argv]
    opts, argv = pop_opts(argv)
    opts = base_opts + (opts or DEFAULT_VARIANT)
    variant = parse_options(opts)
    base = parse_options(base_opts)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    rows = []
    for num, s, mask in iter_broad(select):
        e0 = calibrate(s, base, allow_weak=True)
        e1 = calibrate(s, variant, allow_weak=True)
        err0 = orientation_error(e0.quat, s.quat, mask, s.rate).rms_deg
        err1 = orientation_error(e1.quat, s.quat, mask, s.rate).rms_deg
        kf = np.asarray(e1.info["keyframe_samples"])
        dt = float(np.median(np.diff(s.t[kf])))
        v_opt = optical_velocities(np.asarray(loadmat(s.source)["opt_pos"], float), kf, s.rate)
        sig_o, tau_o = optical_process(v_opt, dt)
        sig1, tau1 = np.asarray(e1.info["velocity_sigma"]), np.asarray(e1.info["velocity_tau"])
        rows.append({"trial": num, "base": round(err0, 3), "variant": round(err1, 3),
                     "diff": round(err1 - err0, 3), "sigma_v": _r(sig1), "tau_v": _r(tau1),
                     "opt_sigma": round(sig_o, 3), "opt_tau": round(tau_o, 3),
                     "opt_step_base": round(normalised_step(v_opt, dt, base.velocity_sigma, base.velocity_tau), 2),
                     "opt_step_var": round(normalised_step(v_opt, dt, sig1, tau1), 2),
                     "rounds": (len(e0.info["history"]), len(e1.info["history"]))})
        print(rows[-1], flush=True)
    means = print_variant_summary(rows, "v1_velocity_process", argv[0] if argv else "", opts)
    if means is None:
        return 2
    m0, m1 = means
    write_json("v1_velocity_process.json", {"rows": rows, "means": {"base": m0, "variant": m1},
                                            "variant_options": opts, "base_options": base_opts})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
