"""H10 (issue 2c): is a constant accelerometer calibration error (scale, skew, misalignment, offset) the cause
of the slow tilt of BROAD 06/15/16? Evidence with the optical truth (diagnostic only), then the product's map.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/h10_acc_map.py truth [TRIALS]
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/h10_acc_map.py windows [TRIALS] [--max-rate R]
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/h10_acc_map.py calibrate [TRIALS] [--map own|loo|truth|truth_loo]
        [--subset all|slow|qs] [--opt FIELD=VALUE ...]

truth: per trial, the linear least-squares fit (optical truth as reference, never used by the product)

    b_acc = Ka·f_opt + ba + e,   f_opt = Rᵀ(p̈ + g e_z) + [ω̇]×r + [ω]×²r                       (T1)

(R = opt_quat, p = opt_pos, p̈ by a Savitzky–Golay second derivative over 0.2 s; ω the gyro; r the lever arm
from the optical body origin to the accelerometer; both sides low-passed alike over 0.1 s; every 10th sample)
on two subsets: "qs" (|ω| < 0.5 rad/s and |p̈| < 0.3 m/s²: close to quasi-static, the ellipsoid's samples) and
"slow" (|ω| < 1.5 rad/s and |p̈| < 1 m/s²: many orientations, little dynamics) and "all" (every sample with a
valid optical pose). Printed: Ka − I split into its symmetric part (scale and
skew: what an ellipsoid sees) and its antisymmetric part (a rotation: the accelerometer's misalignment to the optical
frame — invisible to any ellipsoid), ba, the OLS standard errors, and the tilt the fitted error makes at rest and
over the trial (RMS angle between Ka⁻¹(b_acc − ba) and b_acc over `movement`). Across trials (one IMU in all BROAD
trials, data README): inverse-variance pooled values and Cochran Q/(n−1) (≈ 1 when the trials agree).

windows: the product's quasi-static windows per trial (imugraph/calibration/acc_map.py): how many, in how many
orientations, the coverage gate's verdict, and |b_acc| at rest (the same orientation in every trial).

calibrate: calibrate + score as benchmarks/broad_published.py, raw accelerometer against a corrected one:
own = each trial's own map (acc_map.session_acc_map, gated); loo = the map fitted on the pooled quasi-static windows
of the other trials; truth = the trial's own optical fit (T1, "all", Ka⁻¹ incl. its rotation: an oracle bound);
truth_loo = the pooled optical fit of the other trials; truth_group = that of the other trials in its GROUP.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts, print_table  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.acc_map import (G_NOMINAL, AccMapError, fit_acc_map, quasi_static_windows,  # noqa: E402
                                          session_acc_map)
from imugraph.geometry import quat_to_rotmat  # noqa: E402

DEG = 180 / np.pi
# trials that rest in the same orientation with the same |b_acc| (the `windows` mode: direction, |acc| median) —
# presumably one recording session each; truth_group applies the pooled optical map of the group's other trials
GROUPS = (("01", "04", "06", "10", "15"), ("02", "07", "12", "24", "26"), ("16", "21", "28", "30", "32", "34", "36"))
STEP = 10          # every 10th sample in the truth fit (the low-pass makes neighbours alike)


def _opt_pos(s) -> np.ndarray:
    from scipy.io import loadmat
    return np.asarray(loadmat(s.source, variable_names=["opt_pos"])["opt_pos"], float)


def truth_fit(s, subset: str, shift: int = 0, sigma_s: float = 0.05) -> dict:
    """The least-squares fit (T1) of one trial in the nav frame, both sides smoothed by the same Gaussian K:

        K*(R·b_acc) − g e_z − K''*p = K*[R (Ka − I) f] + K*[R ba] + K*[R ([ω̇]× + [ω]×²) r]

    (f = Rᵀ(p̈ + g e_z) with p̈ = K''*p in the regressor only). Returns Ka − I (3×3), ba, r, their std, residual
    RMS (m/s² per axis), rows."""
    from scipy.ndimage import gaussian_filter1d

    rate, sig = s.rate, sigma_s * s.rate
    K = lambda x, order=0: gaussian_filter1d(x, sig, axis=0, order=order, mode="nearest")   # noqa: E731
    q = np.roll(s.quat, shift, axis=0)
    p = np.roll(_opt_pos(s), shift, axis=0)
    good = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
    qf = np.where(good[:, None], q, [1.0, 0, 0, 0])
    R = quat_to_rotmat(qf / np.linalg.norm(qf, axis=1, keepdims=True))
    pf = np.where(good[:, None], p, 0.0)
    d2 = np.zeros_like(pf)
    d2[1:-1] = (pf[2:] - 2 * pf[1:-1] + pf[:-2]) * rate ** 2
    pdd = K(d2)        # = K''*p exactly (scipy's truncated order-2 kernel does not sum to 0: 0.5 m/s² at rest)
    f = np.einsum("nji,nj->ni", R, pdd + [0, 0, G_NOMINAL])
    wd = np.gradient(K(s.gyr), 1 / rate, axis=0)
    w = s.gyr
    lhs = K(np.einsum("nij,nj->ni", R, s.acc)) - [0, 0, G_NOMINAL] - pdd
    cols = []
    for i in range(3):
        for j in range(3):
            cols.append(K(R[:, :, i] * f[:, j:j + 1]))
    for i in range(3):
        cols.append(K(R[:, :, i]))
    for k in range(3):
        e = np.zeros(3); e[k] = 1.0
        cols.append(K(np.einsum("nij,nj->ni", R, np.cross(wd, e) + np.cross(w, np.cross(w, e)))))
    n_gap = int(4 * sig) + 1
    good = np.convolve(good.astype(float), np.ones(2 * n_gap + 1), mode="same") > 2 * n_gap + 0.5
    if subset in ("qs", "slow"):
        w_max, a_max = (0.5, 0.3) if subset == "qs" else (1.5, 1.0)
        good &= (np.linalg.norm(K(w), axis=1) < w_max) & (np.linalg.norm(pdd, axis=1) < a_max)
    idx = np.flatnonzero(good)[::STEP]
    if len(idx) < 50:
        return {"rows": len(idx)}
    X = np.stack([c[idx] for c in cols], axis=2).reshape(-1, 15)
    Y = lhs[idx].reshape(-1)
    sol, *_ = np.linalg.lstsq(X, Y, rcond=None)
    res = Y - X @ sol
    sig2 = float(res @ res) / (len(Y) - 15)
    cov = np.linalg.pinv(X.T @ X) * sig2 * max(1.0, 3 * sig / STEP)   # rows within ~3σ of K are correlated
    std = np.sqrt(np.diag(cov))
    return {"rows": len(idx), "M": sol[:9].reshape(3, 3), "M_std": std[:9].reshape(3, 3), "ba": sol[9:12],
            "ba_std": std[9:12], "r": sol[12:15], "rms": float(np.sqrt(sig2)), "shift": shift,
            "rms_lhs": float(np.sqrt(np.mean(Y ** 2)))}


def best_truth_fit(s, subset: str) -> dict:
    fits = [truth_fit(s, subset, sh) for sh in (-2, -1, 0, 1, 2)]
    fits = [f for f in fits if "M" in f]
    return min(fits, key=lambda f: f["rms"]) if fits else {"rows": 0}


def tilt_of(Kinv: np.ndarray, ba: np.ndarray, acc: np.ndarray, mask: np.ndarray) -> float:
    """RMS angle (deg) between the corrected and the raw specific force over mask (low-passed 0.2 s)."""
    a = acc[mask]
    c = (a - ba) @ Kinv.T
    cosang = np.sum(a * c, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(c, axis=1))
    return float(np.sqrt(np.mean(np.arccos(np.clip(cosang, -1, 1)) ** 2)) * DEG)


def pooled(vals: np.ndarray, ses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = 1 / ses ** 2
    mean = (w * vals).sum(0) / w.sum(0)
    Q = (w * (vals - mean) ** 2).sum(0) / (len(vals) - 1)
    return mean, 1 / np.sqrt(w.sum(0)), Q


def run_truth(select) -> int:
    keep = {"qs": [], "slow": [], "all": []}
    for num, s, mask in iter_broad(select):
        for subset in keep:
            f = best_truth_fit(s, subset)
            if "M" not in f:
                print(f"{num} {subset}: {f['rows']} rows, no fit")
                continue
            M, Ms = f["M"], f["M_std"]
            sym, asym = (M + M.T) / 2, (M - M.T) / 2
            Kinv = np.linalg.inv(np.eye(3) + M)
            Kinv_sym = np.linalg.inv(np.eye(3) + sym)
            keep[subset].append((num, f))
            print(f"{num} {subset:3s}: rows {f['rows']:5d} shift {f['shift']:+d} "
                  f"rms {f['rms_lhs']:.3f}→{f['rms']:.3f} m/s²  "
                  f"sym diag % {' '.join(f'{100 * v:+.2f}' for v in np.diag(sym))}  sym off % "
                  f"{' '.join(f'{100 * sym[i, j]:+.2f}' for i, j in ((0, 1), (0, 2), (1, 2)))}  rot ° "
                  f"{' '.join(f'{DEG * asym[i, j]:+.2f}' for i, j in ((2, 1), (0, 2), (1, 0)))}  "
                  f"(std % ≤ {100 * Ms.max():.2f})  ba {' '.join(f'{v:+.3f}' for v in f['ba'])} "
                  f"(± {f['ba_std'].max():.3f})  r cm {' '.join(f'{100 * v:+.1f}' for v in f['r'])}  "
                  f"tilt RMS full {tilt_of(Kinv, f['ba'], s.acc, mask):.3f}° sym+ba "
                  f"{tilt_of(Kinv_sym, f['ba'], s.acc, mask):.3f}°", flush=True)
    for subset, rows in keep.items():
        if len(rows) < 2:
            continue
        vals = np.array([np.concatenate([f["M"].ravel(), f["ba"]]) for _, f in rows])
        ses = np.array([np.concatenate([f["M_std"].ravel(), f["ba_std"]]) for _, f in rows])
        mean, se, Q = pooled(vals, ses)
        print(f"pooled {subset} over {len(rows)} trials: Ka−I % {' '.join(f'{100 * v:+.2f}' for v in mean[:9])} "
              f"ba {' '.join(f'{v:+.3f}' for v in mean[9:])}; across-trial SD Ka−I % "
              f"{' '.join(f'{100 * v:.2f}' for v in vals[:, :9].std(0))} "
              f"ba {' '.join(f'{v:.3f}' for v in vals[:, 9:].std(0))}")
        print(f"   Cochran Q/(n−1): {' '.join(f'{v:.0f}' for v in Q)}")
    return 0


def run_windows(select, max_rate: float) -> int:
    rows = []
    for num, s, mask in iter_broad(select):
        y = quasi_static_windows(s.acc, s.gyr, s.rate, max_rate=max_rate)
        row = {"trial": num, "windows": len(y)}
        try:
            m = fit_acc_map(y, source=num)
            row.update(cells=m.n_cells, spread=round(m.spread, 3), verdict="ok")
        except AccMapError as exc:
            row["verdict"] = str(exc).split(": found ")[1][:60]
        nrm = np.linalg.norm(y, axis=1)
        row["|acc| med"] = round(float(np.median(nrm)), 3) if len(y) else None
        u = np.median(y, axis=0) / np.median(nrm) if len(y) else np.zeros(3)
        row["dir"] = " ".join(f"{v:+.3f}" for v in u)
        rows.append(row)
        print(row, flush=True)
    print_table(rows, list(dict.fromkeys(k for r in rows for k in r)))
    return 0


def _truth_maps(select_all: set | None, subset: str) -> dict:
    """{trial: (M, ba, M_std, ba_std)} optical fits (T1 on subset) of every BROAD trial (truth* variants)."""
    out = {}
    for num, s, _ in iter_broad(select_all):
        f = best_truth_fit(s, subset)
        if "M" in f:
            out[num] = (f["M"], f["ba"], f["M_std"], f["ba_std"])
    return out


def corrected(acc: np.ndarray, M: np.ndarray, ba: np.ndarray) -> np.ndarray:
    """f̂ = (I + M)⁻¹(b_acc − ba): the accelerometer corrected by a fitted b_acc = (I + M) f + ba."""
    return np.linalg.solve(np.eye(3) + M, (acc - ba).T).T


def run_calibrate(select, variant: str, options, subset: str = "all") -> int:
    """Calibrate + score each trial with the raw accelerometer and with the corrected one (variant)."""
    from benchmarks.b1_try import vqf_cached
    from imugraph.calibration.ml import calibrate
    from imugraph.evaluate import orientation_error

    truth = _truth_maps(None, subset) if variant.startswith("truth") else {}
    windows = {}
    if variant == "loo":
        windows = {num: quasi_static_windows(s.acc, s.gyr, s.rate) for num, s, _ in iter_broad(None)}
    rows = []
    for num, s, mask in iter_broad(select):
        note = ""
        if variant == "own":
            try:
                m = session_acc_map(s)
                acc = m.apply(s.acc)
            except AccMapError as exc:
                acc, note = None, str(exc).split(": found ")[1][:50]
        elif variant == "loo":
            y = np.concatenate([w for k, w in windows.items() if k != num])
            try:
                m = fit_acc_map(y, source=f"pooled without {num}")
                acc = m.apply(s.acc)
            except AccMapError as exc:
                acc, note = None, str(exc).split(": found ")[1][:50]
        elif variant in ("truth", "truth_sym"):
            M, ba = truth[num][:2]
            acc = corrected(s.acc, M if variant == "truth" else (M + M.T) / 2, ba)
        elif variant in ("truth_loo", "truth_group"):
            donors = next((g for g in GROUPS if num in g), ()) if variant == "truth_group" else truth
            others = [v for k, v in truth.items() if k != num and k in donors]
            if not others:
                acc, note = None, "no donor"
                others = [truth[num]]
            w = [1 / np.concatenate([v[2].ravel(), v[3]]) ** 2 for v in others]
            x = [np.concatenate([v[0].ravel(), v[1]]) for v in others]
            mean = np.sum([a * b for a, b in zip(w, x)], axis=0) / np.sum(w, axis=0)
            acc = corrected(s.acc, mean[:9].reshape(3, 3), mean[9:]) if note != "no donor" else None
        else:
            raise SystemExit(f"--map {variant!r}: expected own, loo, truth, truth_sym, truth_loo or truth_group")
        t0 = time.process_time()
        base = calibrate(s, options, allow_weak=True).quat
        t1 = time.process_time()
        row = {"trial": num}
        row.update(zip(("base", "base_incl", "base_head"), error_parts(base, s, mask)))
        if acc is not None:
            var = calibrate(replace(s, acc=acc), options, allow_weak=True).quat
            row.update(zip(("variant", "var_incl", "var_head"), error_parts(var, s, mask)))
            row["diff"] = row["variant"] - row["base"]
        row["offline_vqf"] = orientation_error(vqf_cached(num, s), s.quat, mask, s.rate).rms_deg
        row = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}
        row["cpu_base_s"] = round(t1 - t0, 2)
        row["note"] = note
        rows.append(row)
        print(row, flush=True)
    print_table(rows, list(dict.fromkeys(k for r in rows for k in r)))
    done = [r for r in rows if "variant" in r]
    if done:
        print(f"{len(done)} trials with a map: mean base {np.mean([r['base'] for r in done]):.3f}°, variant "
              f"{np.mean([r['variant'] for r in done]):.3f}°; largest increase {max(r['diff'] for r in done):+.3f}°; "
              f"variant {variant}")
    return 0


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--map", "--max-rate", "--subset"), max_args=2,
                 values={"--max-rate": float})
    opts, argv = pop_opts(argv)
    flags = {"--map": "own", "--max-rate": "0.3", "--subset": "all"}
    for flag in flags:
        if flag in argv:
            i = argv.index(flag)
            flags[flag] = argv[i + 1]
            argv = argv[:i] + argv[i + 2:]
    mode = argv[0] if argv else "truth"
    select = set(argv[1].split(",")) if len(argv) > 1 else None
    if mode in ("truth", "windows", "calibrate"):
        check_trials(select)
    if mode == "truth":
        return run_truth(select)
    if mode == "windows":
        return run_windows(select, float(flags["--max-rate"]))
    if mode == "calibrate":
        return run_calibrate(select, flags["--map"], parse_options(opts), flags["--subset"])
    print(f"h10_acc_map: unknown mode {mode!r}; expected truth, windows or calibrate", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
