"""H4 (issue 2c): where imugraph's error exceeds offline VQF's, from orientations kept by h4_decompose.py.

    .venv/bin/python benchmarks/h4_decompose.py 02,06,15,16 --tag on        # calibrate, keep bench_out/h4/*.npz
    .venv/bin/python benchmarks/h4_error_split.py 02,06,15,16 --tag on

Per trial, both estimates at their own best alignment (evaluate: shift ±3 samples, constant heading removed):
  * slow (> 2 s, moving average over 2 s) and fast (the rest) parts of the tilt and heading errors (RMS, deg);
  * the slow tilt about magnetic north (imugraph's nav x, where the magnetometer and heading share one field
    component) and about west;
  * the excess (imugraph² − VQF²) of the squared mean tilt / heading error per 2 s window, correlated with the
    window's mean |ω| and | |b_acc| − g |, and its mean over the faster and slower half of the windows.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad  # noqa: E402
from benchmarks.h4_decompose import CACHE  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.evaluate import _align, _scored_index  # noqa: E402

WIN_S = 2.0


def split(q, s, mask):
    """(scored indices, tilt (M, 2) deg in the reference's nav x/y, heading (M,) deg, ψ rad) at the best alignment."""
    al = _align(q, s.quat, mask, 3.0, 0.25, True)
    idx = _scored_index(q, s.quat, mask, 4)
    w, x, y, z = al.q_err
    sign = np.sign(w)
    tilt = np.rad2deg(2 * np.c_[x, y] * sign[:, None])
    head = (np.rad2deg(2 * np.arctan2(z, w)) + 180) % 360 - 180
    return idx, tilt, head, al.psi, al.shift


def slow(x: np.ndarray, k: int) -> np.ndarray:
    """Moving average over k samples (mean removed first), per column."""
    ker = np.ones(k) / k
    x = np.atleast_2d(x.T).T - np.mean(x, axis=0)
    return np.stack([np.convolve(c, ker, "same") for c in x.T], axis=1)


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--tag",), max_args=1)
    tag = "on"
    if "--tag" in argv:
        i = argv.index("--tag")
        tag = argv[i + 1]
        argv = argv[:i] + argv[i + 2:]
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        f = CACHE / f"{num}_{tag}.npz"
        if not f.is_file() or not (CACHE / f"vqf_{num}.npy").is_file():
            print(f"{num}: run benchmarks/h4_decompose.py {num} --tag {tag} first", file=sys.stderr)
            continue
        k = int(WIN_S * s.rate)
        parts = {}
        for name, q in (("imugraph", np.load(f)["quat"]), ("offline VQF", np.load(CACHE / f"vqf_{num}.npy"))):
            idx, tilt, head, psi, shift = split(q, s, mask)
            parts[name] = (idx, tilt, head)
            if name == "imugraph":
                north = np.array([np.cos(psi), np.sin(psi)])       # imugraph's nav x in the reference frame
            st, sh = slow(tilt, k), slow(head[:, None], k)[:, 0]
            ft, fh = tilt - tilt.mean(0) - st, head - head.mean() - sh
            tn, tw = st @ north, st @ np.array([-north[1], north[0]])
            print(f"{num} {name:11s} shift {shift:+.2f}  tilt slow {np.sqrt(np.mean(np.sum(st**2, 1))):.3f} fast "
                  f"{np.sqrt(np.mean(np.sum(ft**2, 1))):.3f} (slow about north {np.sqrt(np.mean(tn**2)):.3f}, west "
                  f"{np.sqrt(np.mean(tw**2)):.3f})  heading slow {np.sqrt(np.mean(sh**2)):.3f} fast "
                  f"{np.sqrt(np.mean(fh**2)):.3f}")
        idx = parts["imugraph"][0]
        if not np.array_equal(idx, parts["offline VQF"][0]):
            continue
        rate = np.linalg.norm(s.gyr, axis=1)[idx]
        dev = np.abs(np.linalg.norm(s.acc, axis=1) - np.median(np.linalg.norm(s.acc, axis=1)))[idx]
        rows = []
        for j in range(len(idx) // k):
            sl = slice(j * k, (j + 1) * k)
            mo, mv = parts["imugraph"], parts["offline VQF"]
            to, tv = mo[1][sl].mean(0), mv[1][sl].mean(0)
            rows.append((rate[sl].mean(), dev[sl].mean(), to @ to - tv @ tv, mo[2][sl].mean() ** 2 - mv[2][sl].mean() ** 2))
        r = np.array(rows)
        fast = r[:, 0] > np.median(r[:, 0])
        for name, c in (("tilt²", 2), ("heading²", 3)):
            print(f"   excess {name:8s} per {WIN_S:.0f} s window: corr with |ω| {np.corrcoef(r[:, 0], r[:, c])[0, 1]:+.2f}, "
                  f"with ||a|−g| {np.corrcoef(r[:, 1], r[:, c])[0, 1]:+.2f}; mean in the faster half "
                  f"{r[fast, c].mean():+.3f}, slower half {r[~fast, c].mean():+.3f} deg²")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
