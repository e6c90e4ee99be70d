"""B1 (issue 2c): score one Options variant on chosen BROAD trials against cached offline VQF: total,
inclination and heading RMS, the estimated dip and the mean nav-frame tilt error (deg).

    .venv/bin/python benchmarks/b1_try.py 01,04 --opt velocity_sigma=0.1 [--opt ...]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks.output import OUT_DIR  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import _align  # noqa: E402

CACHE = OUT_DIR / "b1"     # offline VQF and our quaternions per trial, reused by the b1 scripts
TAG = "last"


def parse_opts(argv):
    """(ml.Options from the `--opt FIELD=VALUE` pairs, the rest of argv)."""
    opts, rest = pop_opts(argv)
    return parse_options(opts), rest


def nav_tilt_mean(q, s, mask):
    from scipy.spatial.transform import Rotation as Rot
    al = _align(q, s.quat, mask, 3.0, 0.25, True)
    e = Rot.from_quat(np.c_[al.q_err.T[:, 1:], al.q_err.T[:, :1]]).as_rotvec()
    return np.rad2deg(e.mean(0)[:2]), np.rad2deg(e.std(0)[:2])


def compare_line(label: str, q, q_vqf, s, mask) -> str:
    """'label: ours total (incl, head)  offVQF total (incl, head)' in degrees."""
    o, v = error_parts(q, s, mask), error_parts(q_vqf, s, mask)
    return (f"{label}: ours {o[0]:.3f} (incl {o[1]:.2f} head {o[2]:.2f})  offVQF {v[0]:.3f} "
            f"(incl {v[1]:.2f} head {v[2]:.2f})")


def vqf_cached(num, s, cache: Path = CACHE):
    """Offline VQF's orientation of trial `num` (computed once, then read from cache/vqf_<num>.npy)."""
    f = cache / f"vqf_{num}.npy"
    if f.is_file():
        return np.load(f)
    q = vqf_offline(s)
    cache.mkdir(parents=True, exist_ok=True)
    np.save(f, q)
    return q


def main(argv):
    global TAG
    exit_on_help(__doc__, argv, flags=("--opt", "--tag"), max_args=1)
    options, argv = parse_opts(argv)
    if "--tag" in argv:
        i = argv.index("--tag"); TAG = argv[i + 1]; argv = argv[:i] + argv[i + 2:]
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    tot = []
    for num, s, mask in iter_broad(select):
        t0 = time.perf_counter()
        est = calibrate(s, options, allow_weak=True)
        dt = time.perf_counter() - t0
        qv = vqf_cached(num, s)
        o = list(error_parts(est.quat, s, mask))
        v = list(error_parts(qv, s, mask))
        m, sd = nav_tilt_mean(est.quat, s, mask)
        tot.append((o[0], v[0]))
        print(f"{num} ours {o[0]:.3f} (incl {o[1]:.2f} head {o[2]:.2f})  offVQF {v[0]:.3f} (incl {v[1]:.2f} head "
              f"{v[2]:.2f})  dip {est.calibration.dip_deg:.2f}  tiltE/N mean {m.round(2)} std {sd.round(2)} "
              f"g {est.info['g']:.4f} {dt:.1f}s", flush=True)
        np.save(CACHE / f"ours_{num}_{TAG}.npy", est.quat)
    a = np.array(tot)
    print(f"mean ours {a[:, 0].mean():.3f} offVQF {a[:, 1].mean():.3f} ratio {a[:, 0].mean() / a[:, 1].mean():.3f} "
          f"worse {int(np.sum(a[:, 0] > a[:, 1]))}/{len(a)}  opts {options}")


if __name__ == "__main__":
    main(sys.argv[1:])
