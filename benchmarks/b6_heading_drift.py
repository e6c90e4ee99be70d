"""B6 (issue 2c, trials 15/16): where does the heading error of the fast translation trials come from?

    .venv/bin/python benchmarks/b6_heading_drift.py 15,16 [--opt FIELD=VALUE ...]

For imugraph (calibrate, Options from --opt) and offline VQF, the signed heading error over `movement` at
the evaluation's alignment (imugraph.evaluate: best shift and constant heading), smoothed over 2 s, is set
beside the azimuth of the field the magnetometer sees in the optical nav frame (n_m = R_opt · D⁻¹(y − o),
with imugraph's D, o; deviation from its mean; also smoothed over 2 s) and the optical position. Printed:
RMS of each heading error; the least-squares slope and R² of each heading error on the field-azimuth
deviation; the R² of a linear function of position (opt_pos) for both; and the RMS of the field-azimuth
deviation itself. Hypothesis: the field direction varies with position (translation), and a heading that
follows the magnetometer inherits it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import _align, _scored_index  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402


def signed_heading(q: np.ndarray, s, mask) -> tuple[np.ndarray, np.ndarray]:
    """(scored sample indices, signed heading error deg) at the evaluation's alignment."""
    al = _align(q, s.quat, mask, 3.0, 0.25, True)
    idx = _scored_index(q, s.quat, mask, 4)
    w, z = al.q_err[0], al.q_err[3]
    sign = np.where(w < 0, -1.0, 1.0)
    return idx, np.rad2deg(2.0 * np.arctan2(sign * z, sign * w))


def smooth(x: np.ndarray, n: int) -> np.ndarray:
    c = np.convolve(x, np.ones(n) / n, mode="same")
    return c


def fit(y: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, float]:
    """Least squares y ≈ X β: (β, R²)."""
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ beta
    return beta, 1.0 - float(np.sum(r**2) / np.sum((y - y.mean()) ** 2))


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, rest = pop_opts(argv)
    if not rest:
        usage_error("expected TRIALS (e.g. 15,16)")
    check_trials(set(rest[0].split(",")))
    options = parse_options(opts)
    from scipy.io import loadmat

    for num, s, mask in iter_broad(set(rest[0].split(","))):
        est = calibrate(s, options, allow_weak=True)
        q_v = vqf_offline(s)
        pos = np.asarray(loadmat(s.source)["opt_pos"], float)
        D, o = est.calibration.D, est.calibration.o
        m_b = np.linalg.solve(D, (s.mag - o).T).T
        m_n = np.einsum("nij,nj->ni", quat_to_rotmat(s.quat), m_b)
        az = np.arctan2(m_n[:, 1], m_n[:, 0])
        fin = np.isfinite(az)
        az[fin] = np.unwrap(az[fin])            # NaN where the optical orientation is missing
        n2 = int(2 * s.rate)
        print(f"{num} {s.name}")
        for name, q in (("imugraph", est.quat), ("offline VQF", q_v)):
            idx, h = signed_heading(q, s, mask)
            a_i = az[idx]
            good = np.isfinite(a_i)
            a_i = np.interp(np.arange(len(a_i)), np.flatnonzero(good), a_i[good])   # fill gaps before smoothing
            ok = np.all(np.isfinite(pos[idx]), axis=1)
            hs = smooth(h, n2)[ok]
            a = smooth(np.rad2deg(a_i - a_i.mean()), n2)[ok]
            a = a - a.mean()
            beta, r2 = fit(hs - hs.mean(), a[:, None])
            _, r2p = fit(hs, np.c_[np.ones(ok.sum()), pos[idx][ok]])
            print(f"   {name:11s}: heading RMS {np.sqrt(np.mean(h**2)):.2f}° (2-s smoothed {np.sqrt(np.mean(hs**2)):.2f}°); "
                  f"on field azimuth: slope {beta[0]:+.2f}, R² {r2:.2f}; on position: R² {r2p:.2f}")
        print(f"   field azimuth deviation (2-s smoothed) RMS {np.sqrt(np.mean(a**2)):.2f}°; "
              f"position span {np.nanmax(pos, 0) - np.nanmin(pos, 0)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
