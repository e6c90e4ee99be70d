"""Regression check for speed work on calibrate: run it on BROAD trials, store the results, compare two runs.

    .venv/bin/python benchmarks/b6_regress.py run TAG TRIALS [--opt FIELD=VALUE ...]
    .venv/bin/python benchmarks/b6_regress.py cmp TAG_A TAG_B

`run` calibrates each trial (comma-separated two-digit numbers) with Options from --opt, one BLAS thread,
and stores per trial the per-sample quaternions, θ, noise levels, Ê, the RMS error against opt_quat
(evaluate.orientation_error over `movement`) and the CPU time (process_time) in /tmp/b6_regress/TAG/NN.npz.
`cmp` prints, per trial, the largest per-sample angle between the two runs' orientations, the largest θ
change, both RMS errors and both CPU times. Nothing is written into the repository.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_v] = "1"

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks._usage import exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402
from imugraph.factors.theta import pack_theta  # noqa: E402
from imugraph.geometry import quat_conj, quat_mul  # noqa: E402

ROOT = Path("/tmp/b6_regress")


def run(tag: str, trials: str, opts: list[str]) -> None:
    options = parse_options(opts)
    out = ROOT / tag
    out.mkdir(parents=True, exist_ok=True)
    for num, s, mask in iter_broad(set(trials.split(","))):
        c0 = time.process_time()
        est = calibrate(s, options, allow_weak=True)
        cpu = time.process_time() - c0
        cal = est.calibration
        rms = orientation_error(est.quat, s.quat, mask, s.rate).rms_deg
        gate = est.info.get("gyro_map_gate", {})
        np.savez(out / f"{num}.npz", quat=est.quat, theta=pack_theta(cal.D, cal.o, np.deg2rad(cal.dip_deg)),
                 noise=np.concatenate([np.ravel(cal.noise[k]) for k in ("gyr", "acc", "mag")]),
                 E=np.asarray(est.info.get("gyro_map", np.zeros((3, 3)))), rms=rms, cpu=cpu,
                 estimated=bool(gate.get("estimated", False)), rounds=len(est.info["history"]),
                 lm=sum(h["lm_iterations"] for h in est.info["history"] + gate.get("rounds", []))
                 + est.info["lm_iterations_final"])
        lm = sum(h["lm_iterations"] for h in est.info["history"] + gate.get("rounds", [])) + est.info["lm_iterations_final"]
        print(f"{tag} {num}: RMS {rms:.4f}°, CPU {cpu:.2f} s, rounds {len(est.info['history'])}, LM iterations {lm}, "
              f"gyro_map estimated {gate.get('estimated')}", flush=True)


def angle_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Angle (deg) of q_a* ⊗ q_b per sample, 2·asin|vec| (accurate near zero, unlike acos of a trace)."""
    qa = qa / np.linalg.norm(qa, axis=1, keepdims=True)
    qb = qb / np.linalg.norm(qb, axis=1, keepdims=True)
    rel = quat_mul(quat_conj(qa), qb)
    return np.rad2deg(2.0 * np.arcsin(np.clip(np.linalg.norm(rel[:, 1:], axis=1), 0.0, 1.0)))


def cmp(tag_a: str, tag_b: str) -> None:
    for fa in sorted((ROOT / tag_a).glob("*.npz")):
        fb = ROOT / tag_b / fa.name
        if not fb.exists():
            continue
        a, b = np.load(fa), np.load(fb)
        dq = float(np.nanmax(angle_deg(a["quat"], b["quat"])))
        dth = float(np.max(np.abs(a["theta"] - b["theta"])))
        print(f"{fa.stem}: max Δangle {dq:.2e}°, max Δθ {dth:.2e}, RMS {float(a['rms']):.4f} → "
              f"{float(b['rms']):.4f}°, CPU {float(a['cpu']):.2f} → {float(b['cpu']):.2f} s, rounds "
              f"{int(a['rounds'])} → {int(b['rounds'])}")


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",))
    opts, rest = pop_opts(argv)
    if len(rest) == 3 and rest[0] == "run":
        run(rest[1], rest[2], opts)
    elif len(rest) == 3 and rest[0] == "cmp":
        cmp(rest[1], rest[2])
    else:
        usage_error("expected `run TAG TRIALS [--opt FIELD=VALUE ...]` or `cmp TAG_A TAG_B`")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
