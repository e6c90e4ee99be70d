"""H8 (issue 2c/2b): is the slow tilt drift of BROAD 06/15/16 a gyro g-sensitivity? Evidence with the optical truth.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/h8_gsens.py [02,06,...] [--win 1.0] [--model base|split|rate2|g2]
        [--ref opt|vqf|TAG] [--halves] [--oracle [--opt FIELD=VALUE ...]]

--oracle: the upper bound of any g-sensitivity model: each trial calibrated (default Options, or --opt FIELD=VALUE)
four times — raw gyro; gyro corrected by its own optically fitted G (ω − G·f), S's symmetric part (ω − S·ω), both —
and scored like broad_published.py (RMS over `movement`, best shift, heading removed) beside offline VQF.

--halves: also fit the first and the second half of each trial's `movement` samples apart and print, per block,
the RMS over its elements of z = (θ₁ − θ₂)/√(σ₁² + σ₂²): ≈ 1 when the block is constant within the trial and the
standard errors are right (the calibration of Cochran's Q across trials).

--ref: the reference orientation: opt (default, the optical truth), vqf (offline VQF, bench_out/h4/vqf_NN.npy) or
TAG (imugraph's, bench_out/h4/NN_TAG.npz kept by benchmarks/h4_decompose.py): then the fit says which gyro error
that estimate's orientation implies — the difference to the optical fit is the part of its error that follows
the regressors (e.g. a tilt error that follows the specific force).

Per trial, the gyro error model (1) of imugraph/calibration/gyro_gsens.py,

    δω_j = b(t_j) + G·f_j + S·ω_meas,j [+ K·(ω_meas,j ⊙ |ω_meas,j|)]   (f: specific force in g)

fitted through the window relation (2) there against the optical quaternions (`opt_quat`, at the lag with the
smallest residual) over the `movement` windows: G (°/s per g) with its OLS standard error, the Wald F-test of
G = 0, S's diagonal (%), and what the fitted G does to the orientation: the RMS rotation its linear-acceleration
part G·(f − g_b) and its gravity part G·g_b accumulate over 10 s windows (g_b from the optical orientation).
Across trials (one IMU in every BROAD trial, so a physical G is the same in each): the inverse-variance pooled
value and Cochran's Q/(n−1) per element (≈ 1 when consistent).

--model split fits G_grav·g_b + G_lin·(f − g_b) separately (a physical g-sensitivity has G_lin = G_grav);
--model rate2 adds the per-component rate-squared scale K (°/s per (rad/s)²); --model g2 the g²-sensitivity G₂
(°/s per g² of each specific-force component).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks.h4_decompose import CACHE  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.gyro_gsens import G0, fit_gyro_errors, pooled, predicted_rotation  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402

DEG = 180 / np.pi
IMPACT_WIN_S = 10.0


def fmt3(G: np.ndarray, se: np.ndarray) -> str:
    return " ".join(f"{g:+.3f}±{e:.3f}" for g, e in zip(G.ravel(), se.ravel()))


def run_oracle(num: str, s, mask: np.ndarray, fit, options) -> None:
    """Calibrate the trial with the raw gyro, ω − G·f, ω − S·ω and ω − G·f − S·ω (G, S: fitted against the truth)."""
    from dataclasses import replace

    from benchmarks.b1_try import vqf_cached
    from imugraph.calibration.ml import calibrate
    from imugraph.evaluate import orientation_error

    G, _ = fit.block("G")
    S, _ = fit.block("S")
    S = (S + S.T) / 2            # scale/non-orthogonality only: S's antisymmetric part is the optical frame's misalignment
    f = s.acc / G0
    variants = {"raw": s.gyr, "−G·f": s.gyr - f @ G.T, "−S·ω": s.gyr - s.gyr @ S.T,
                "−G·f−S·ω": s.gyr - f @ G.T - s.gyr @ S.T}
    scores = {name: orientation_error(calibrate(replace(s, gyr=gyr), options, allow_weak=True).quat, s.quat, mask,
                                      s.rate).rms_deg for name, gyr in variants.items()}
    vqf = orientation_error(vqf_cached(num, s), s.quat, mask, s.rate).rms_deg
    print(f"   oracle: imugraph {', '.join(f'{k} {v:.3f}°' for k, v in scores.items())}; offline VQF {vqf:.3f}°",
          flush=True)


def symmetric_part(fit) -> tuple[np.ndarray, np.ndarray]:
    """(S + Sᵀ)/2 in % and its standard error (from the fit's covariance): scale and non-orthogonality, free of the
    reference's misalignment to the gyro axes (which enters S's antisymmetric part only)."""
    i = fit.index("S")
    est, se = np.zeros((3, 3)), np.zeros((3, 3))
    for r in range(3):
        for c in range(3):
            w = np.zeros(9)
            w[3 * r + c] += 0.5
            w[3 * c + r] += 0.5
            est[r, c] = w @ fit.theta[i]
            se[r, c] = np.sqrt(w @ fit.cov[np.ix_(i, i)] @ w)
    return 100 * est, 100 * se


def gravity_body(quat: np.ndarray) -> np.ndarray:
    """(N, 3) gravity's specific force in the body frame, in g, from body→ENU quaternions (NaN rows → 0)."""
    good = np.all(np.isfinite(quat), axis=1)
    q = np.where(good[:, None], quat, np.array([1.0, 0, 0, 0]))
    g_b = np.einsum("nji,j->ni", quat_to_rotmat(q / np.linalg.norm(q, axis=1, keepdims=True)), np.array([0, 0, 1.0]))
    return np.where(good[:, None], g_b, 0.0)


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--win", "--model", "--ref"), switches=("--halves", "--oracle"),
                 max_args=1, values={"--win": float})
    halves, oracle = "--halves" in argv, "--oracle" in argv
    opts, argv = pop_opts([a for a in argv if a not in ("--halves", "--oracle")])
    flags = {"--win": "1.0", "--model": "base", "--ref": "opt"}
    for flag in flags:
        if flag in argv:
            i = argv.index(flag)
            flags[flag] = argv[i + 1]
            argv = argv[:i] + argv[i + 2:]
    win, model, ref = float(flags["--win"]), flags["--model"], flags["--ref"]
    select = set(argv[0].split(",")) if argv else None
    if model not in ("base", "split", "rate2", "g2"):
        usage_error(f"--model {model!r}: expected base, split, rate2 or g2")
    check_trials(select)
    tags = {"base": ["G"], "split": ["Ggrav", "Glin"], "rate2": ["G", "K"], "g2": ["G", "G2"]}[model]
    print(f"model {model}, reference {ref}, windows {win:g} s; G in °/s per g (row: gyro axis, column: specific-force axis, "
          f"row-major xx xy xz yx ... zz); ± OLS standard error")
    est = {t: [] for t in tags + ["S", "Ssym"]}
    for num, s, mask in iter_broad(select):
        q_ref = s.quat
        if ref == "vqf":
            q_ref = np.load(CACHE / f"vqf_{num}.npy")
        elif ref != "opt":
            q_ref = np.load(CACHE / f"{num}_{ref}.npz")["quat"]
        fit = fit_gyro_errors(s, q_ref, mask, win, model)
        Sd, Se = fit.block("S")
        est["S"].append((100 * Sd, 100 * Se))
        est["Ssym"].append(symmetric_part(fit))
        f_lin = np.sqrt(np.mean((np.linalg.norm(s.acc[mask], axis=1) - G0) ** 2))
        print(f"{num}: lag {fit.lag:+.2f} samples, {fit.windows} windows, residual {fit.sigma * DEG:.3f}° per window, "
              f"||f|−g| RMS {f_lin:.1f} m/s², S diag % "
              f"{' '.join(f'{v:+.3f}±{e:.3f}' for v, e in zip(100 * np.diag(Sd), 100 * np.diag(Se)))}")
        for t in tags:
            G, se = fit.block(t)
            F, p = fit.wald(t)
            est[t].append((G * DEG, se * DEG))
            line = f"   {t:5s} F {F:6.2f} p {p:.1e}  max|t| {np.max(np.abs(G / se)):5.1f}  {fmt3(G * DEG, se * DEG)}"
            if t == "G":
                g_b = gravity_body(s.quat)
                lin = predicted_rotation(s, s.acc / G0 - g_b, G, IMPACT_WIN_S, mask) * DEG
                grav = predicted_rotation(s, g_b, G, IMPACT_WIN_S, mask) * DEG
                line += f"\n         rotation over {IMPACT_WIN_S:g} s windows (RMS): G·f_lin {lin:.4f}°, G·g_b {grav:.4f}°"
            print(line, flush=True)
        if oracle:
            run_oracle(num, s, mask, fit, parse_options(opts))
        if halves:
            idx = np.flatnonzero(mask)
            cut = idx[len(idx) // 2]
            parts = [fit_gyro_errors(s, q_ref, mask & (np.arange(s.n) < cut), win, model),
                     fit_gyro_errors(s, q_ref, mask & (np.arange(s.n) >= cut), win, model)]
            zs = []
            for t in tags + ["S"]:
                (g1, e1), (g2, e2) = parts[0].block(t), parts[1].block(t)
                zs.append(f"{t} {np.sqrt(np.mean(((g1 - g2) / np.hypot(e1, e2)) ** 2)):.2f}")
            print(f"   halves: RMS z of the difference {', '.join(zs)}", flush=True)
    for t in tags + ["S", "Ssym"]:
        if len(est[t]) < 2:
            continue
        mean, pse, Q = pooled(np.array([g for g, _ in est[t]]), np.array([e for _, e in est[t]]))
        unit = ("%" if t.startswith("S") else "°/s per g²" if t == "G2" else "°/s per g" if t.startswith("G")
                else "°/s per (rad/s)²")
        print(f"pooled {t} ({unit}) over {len(est[t])} trials: {fmt3(mean, pse)}")
        print(f"   Cochran Q/(n−1) per element (≈1 if the trials agree): {' '.join(f'{q:.1f}' for q in Q.ravel())}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
