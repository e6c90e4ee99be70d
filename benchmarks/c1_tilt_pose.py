"""C1 (issue 2c): does the inclination error look like an accelerometer bias (sensor frame) or a nav-frame
tilt? Fits the nav-frame tilt error δ (x, y of the error rotation vector, reference frame) of imugraph and
offline VQF as  δ ≈ c + [e_z]× nRb b / g  (c: constant nav tilt, b: sensor-frame accelerometer bias) and
prints c, b, the variance explained, and the error vs |b_acc| at rest.

    .venv/bin/python benchmarks/c1_tilt_pose.py 30,36,02 [--opt FIELD=VALUE ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.b1_try import parse_opts, vqf_cached  # noqa: E402
from benchmarks.common import iter_broad  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import _align  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402


def tilt_fit(q, s, mask, g=9.81):
    from scipy.spatial.transform import Rotation as Rot
    al = _align(q, s.quat, mask, 3.0, 0.25, True)
    d = Rot.from_quat(np.c_[al.q_err.T[:, 1:], al.q_err.T[:, :1]]).as_rotvec()[:, :2]
    idx = np.flatnonzero(mask & np.all(np.isfinite(s.quat), axis=1))
    idx = idx[:len(d)] if len(idx) >= len(d) else idx
    R = quat_to_rotmat(s.quat[idx[:len(d)]])
    d = d[:len(R)]
    # [e_z]× R b: x-row = −(R b)_y, y-row = (R b)_x
    A = np.zeros((len(R), 2, 5))
    A[:, 0, 0] = 1; A[:, 1, 1] = 1
    A[:, 0, 2:] = -R[:, 1, :] / g
    A[:, 1, 2:] = R[:, 0, :] / g
    A2, y = A.reshape(-1, 5), d.reshape(-1)
    p, *_ = np.linalg.lstsq(A2, y, rcond=None)
    c_only = y - np.tile(np.mean(d, axis=0), len(d))
    res = y - A2 @ p
    return p, np.rad2deg(np.sqrt(np.mean(y**2))), np.rad2deg(np.sqrt(np.mean(c_only**2))), np.rad2deg(np.sqrt(np.mean(res**2)))


def main(argv):
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = parse_opts(argv)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        est = calibrate(s, opts, allow_weak=True)
        for name, q in (("ours", est.quat), ("offVQF", vqf_cached(num, s))):
            p, rms, rms_c, rms_cb = tilt_fit(q, s, mask)
            print(f"{num} {name:6s} tilt rms {rms:.2f}° | after const {rms_c:.2f}° | after const+bias {rms_cb:.2f}°  "
                  f"c {np.rad2deg(p[:2]).round(2)}°  b {p[2:].round(3)} m/s²", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
