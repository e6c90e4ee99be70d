"""B1 (issue 2c): decompose the BROAD orientation error of imugraph and offline VQF into inclination and
heading, overall and per time window, and compare gyro biases.

    .venv/bin/python benchmarks/b1_decompose.py 01,04 [--opt field=value ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.b1_try import CACHE, parse_opts  # noqa: E402
from benchmarks.common import error_parts, iter_broad  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def main(argv):
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = parse_opts(argv)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        est = calibrate(s, opts, allow_weak=True)
        import vqf
        out = vqf.offlineVQF(np.ascontiguousarray(s.gyr), np.ascontiguousarray(s.acc),
                             np.ascontiguousarray(s.mag), 1.0 / s.rate)
        q_v = vqf_offline(s)
        a, b = error_parts(est.quat, s, mask), error_parts(q_v, s, mask)
        print(f"{num}: ours tot/incl/head {a[0]:.2f}/{a[1]:.2f}/{a[2]:.2f}  "
              f"offVQF {b[0]:.2f}/{b[1]:.2f}/{b[2]:.2f}")
        print(f"   bias ours {np.rad2deg(est.calibration.gyro_bias).round(3)} °/s  "
              f"VQF mean {np.rad2deg(np.nanmean(out['bias'], axis=0)).round(3)}")
        seg = est.info["gyro_bias_segments"]
        print(f"   our bias segments range (°/s): {np.rad2deg(seg.min(0)).round(3)} .. {np.rad2deg(seg.max(0)).round(3)}")
        print(f"   dip {est.calibration.dip_deg:.2f} noise {est.calibration.noise} g {est.info['g']:.4f}")
        CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(CACHE / f"{num}.npz", q_ours=est.quat, q_vqf=q_v, vqf_bias=out["bias"],
                 bias_seg=seg, kf=est.info["keyframe_samples"])
        # per 20 s window
        n = s.n
        w = int(20 * s.rate)
        line_o, line_v = [], []
        for i0 in range(0, n, w):
            m = mask.copy(); m[:i0] = False; m[i0 + w:] = False
            if m.sum() < 200:
                continue
            try:
                line_o.append(f"{error_parts(est.quat, s, m)[1]:.2f}/{error_parts(est.quat, s, m)[2]:.2f}")
                line_v.append(f"{error_parts(q_v, s, m)[1]:.2f}/{error_parts(q_v, s, m)[2]:.2f}")
            except Exception as exc:
                pass
        print("   20s windows incl/head ours:", " ".join(line_o))
        print("   20s windows incl/head vqf :", " ".join(line_v))


if __name__ == "__main__":
    main(sys.argv[1:])
