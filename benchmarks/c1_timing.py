"""C1 (issue 2c): accelerometer–gyro sample timing on BROAD, the diagnosis behind Options.acc_lead_samples.

Per trial:
  net nav rotation  ∫ n_ω dt over the trial from the reference orientation (rad, nav x, y, z): a timing
                    error δ gives the velocity chain a drift g δΔt (e_z × ∫ n_ω dt) (calibration/acc_timing.py)
  gyro ↔ optical    the shift (samples) of the optical body rate (central differences) that best matches
                    the gyro
  acc ↔ optical     the shift of the optical orientation that makes the accelerometer's 1 s window means
                    most vertical (R(j + s) a_j); with the gyro's shift it gives the accelerometer's timing
                    relative to the forward-rule orientation: δ ≈ s_acc − s_gyr + ½. Confounded, on trials
                    that spin one way about a horizontal axis, with an accelerometer/reference misalignment
                    about that axis
  rest poses        contiguous rests ≥ 1 s and the largest angle between their mean accelerometer
                    directions (a multi-position accelerometer calibration needs several distinct poses)

    .venv/bin/python benchmarks/c1_timing.py [TRIALS]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.rest import detect_rest  # noqa: E402


def net_rotation(s) -> np.ndarray:
    ok = np.all(np.isfinite(s.quat), axis=1)
    idx = np.where(ok, np.arange(s.n), np.argmax(ok))
    np.maximum.accumulate(idx, out=idx)
    R = Rotation.from_quat(s.quat[idx][:, [1, 2, 3, 0]]).as_matrix()
    return np.sum(np.einsum("nij,nj->ni", R, s.gyr) * s.dt[:, None], axis=0)


def optical_shifts(s, shifts=np.arange(-4.0, 4.01, 0.25)):
    ok = np.all(np.isfinite(s.quat), axis=1)
    i = np.flatnonzero(ok)
    sl = Slerp(i.astype(float), Rotation.from_quat(s.quat[i][:, [1, 2, 3, 0]]))
    j = np.arange(i[0] + 10, i[-1] - 10)
    j = j[ok[j]]
    win = int(s.rate)

    def gyro_cost(sh):
        rate = (sl(j - 0.5 + sh).inv() * sl(j + 0.5 + sh)).as_rotvec() * s.rate
        return np.mean(np.sum((s.gyr[j] - rate) ** 2, axis=1))

    def acc_cost(sh):
        f = sl(j + sh).apply(s.acc[j])
        f = f[: len(f) // win * win].reshape(-1, win, 3).mean(axis=1)
        return np.mean(f[:, 0] ** 2 + f[:, 1] ** 2)

    return (float(shifts[np.argmin([gyro_cost(x) for x in shifts])]),
            float(shifts[np.argmin([acc_cost(x) for x in shifts])]))


def rest_poses(s):
    rest = detect_rest(s)
    start = rest & ~np.r_[False, rest[:-1]]
    label = np.where(rest, np.cumsum(start) - 1, -1)
    means = [s.acc[label == k].mean(axis=0) for k in range(label.max() + 1) if np.sum(label == k) >= s.rate]
    if len(means) < 2:
        return len(means), 0.0
    u = np.array(means) / np.linalg.norm(means, axis=1, keepdims=True)
    return len(means), float(np.degrees(np.arccos(np.clip(u @ u.T, -1, 1))).max())


def main(argv):
    exit_on_help(__doc__, argv, flags=(), max_args=1)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, _ in iter_broad(select):
        th = net_rotation(s)
        sg, sa = optical_shifts(s)
        n_rest, spread = rest_poses(s)
        print(f"{num} net nav rotation {np.round(th, 1)} rad | gyro↔optical {sg:+.2f}, acc↔optical {sa:+.2f} "
              f"samples → δ ≈ {sa - sg + 0.5:+.2f} | rests ≥ 1 s: {n_rest}, poses within {spread:.1f}°", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
