"""H9 (issue 2c): would held-out accelerometer prediction choose between the velocity processes ("bounded_ar2",
"free_ar2", ...)? Per trial and variant, the calibration is run once; at its final keyframe orientations the
velocity increments y_k = R_k Δv_k + n_grav Δt_k of 2 s blocks are held out in turn (2 folds) and scored by
their exact predictive density given the other increments under the variant's own process — the marginal
likelihood of the velocity chain by a Kalman filter (calibration/acc_rate.py, eq. 3):

    score_b = ℓ(O_f ∪ H_b) − ℓ(O_f)     (nats; block b of fold f; O_f the increments outside fold f's blocks)

The orientations were solved with every increment (no re-solve per fold: the cheap version of the test, it
favours the process that let the tilt follow the accelerometer). Also each variant's process at the other's
orientations (to split process from orientation). The optical truth only scores (printed beside).

    .venv/bin/python benchmarks/h9_heldout_acc.py 02,07 [--variants bounded_ar2,free_ar2]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import imugraph.calibration.ml as ml  # noqa: E402
from benchmarks.common import error_parts, iter_broad, pop_value  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.acc_rate import marginal_log_lik, process_matrices  # noqa: E402
from imugraph.factors.velocity import velocity_model  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402

BLOCK_S, FOLDS = 2.0, 2


def run(s, mode: str):
    """calibrate with the mode; returns (estimate, the final solve's VelocityBlock, keyframe nRk)."""
    captured = {}
    orig = ml.build_problem

    def build(*a, **k):
        captured["prob"] = orig(*a, **k)
        return captured["prob"]

    ml.build_problem = build
    try:
        est = ml.calibrate(s, ml.Options(estimate_velocity_process=mode), allow_weak=True)
    finally:
        ml.build_problem = orig
    kf = est.info["keyframe_samples"]
    return est, captured["prob"].velocity, quat_to_rotmat(est.quat[kf])


def block_scores(block, nRk: np.ndarray, s: np.ndarray) -> np.ndarray:
    """score_b (module docstring) of every held-out block, in block order."""
    K = block.n_keyframes
    y = -velocity_model(nRk, np.zeros((K, 3)), block.dv, block.dt_k, block.g, None, None)[0]
    _, _, w, *_ = block.terms(nRk, s)
    c0, A = block.sigma_dv**2, np.zeros(K - 1)
    mats = process_matrices(block)
    per = max(1, int(round(BLOCK_S / float(np.median(block.dt_k)))))
    blk = np.arange(K - 1) // per
    out = []
    for f in range(FOLDS):
        train = w.copy()
        train[blk % FOLDS == f] = 1e-12
        base = marginal_log_lik(np.zeros(1), y, c0, A, train, *mats)[0]
        for b in np.unique(blk[blk % FOLDS == f]):
            wb = train.copy()
            wb[blk == b] = w[blk == b]
            # the held-out steps' 1e-12 weights add ½ ln(c0/1e-12) each to `base`: removed, model-independent
            const = 0.5 * 3 * np.sum(np.log(c0[blk == b] / 1e-12))
            out.append((b, marginal_log_lik(np.zeros(1), y, c0, A, wb, *mats)[0] - base - const))
    out.sort()
    return np.array([v for _, v in out])


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--variants",), max_args=1)
    variants, argv = pop_value(argv, "--variants", "bounded_ar2,free_ar2")
    variants = variants.split(",")
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        runs = {m: run(s, m) for m in variants}
        own = {}
        for m, (est, block, nRk) in runs.items():
            line = [f"{num} {m:12s} err {error_parts(est.quat, s, mask)[0]:.3f}°"]
            for m2, (est2, _, nRk2) in runs.items():       # this process at each run's orientations
                sc = block_scores(block, nRk2, np.asarray(est2.info["velocity"], float))
                line.append(f"at R[{m2}]: {sc.sum():9.1f} nats")
                if m2 == m:
                    own[m] = sc
            print("  ".join(line), flush=True)
        if len(variants) == 2:
            d = own[variants[1]] - own[variants[0]]
            z = d.mean() / (d.std(ddof=1) / np.sqrt(len(d)))
            print(f"{num} {variants[1]} − {variants[0]} (own orientations): {d.sum():.1f} nats over {len(d)} blocks, "
                  f"paired z {z:+.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
