"""H4 (issue 2c): decompose the error of one Options variant on chosen BROAD trials into inclination and heading,
overall and per 20 s window, beside offline VQF (cached), and keep the orientations for later comparison.

    .venv/bin/python benchmarks/h4_decompose.py 02,15 --tag map_off --opt gyro_map=False

Writes bench_out/h4/{trial}_{tag}.npz (quat, gyro-map gate) and bench_out/h4/vqf_{trial}.npy.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts, pop_value  # noqa: E402
from benchmarks.output import OUT_DIR  # noqa: E402
from benchmarks.b1_try import vqf_cached  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402

CACHE = OUT_DIR / "h4"


def windows(q, s, mask, win_s: float = 20.0) -> list[tuple[float, float, float]]:
    """(total, inclination, heading) RMS per window of win_s seconds (the alignment of each window's own)."""
    out, w = [], int(win_s * s.rate)
    for i0 in range(0, s.n, w):
        m = mask.copy()
        m[:i0] = False
        m[i0 + w:] = False
        if m.sum() < 200:
            out.append((np.nan,) * 3)
            continue
        out.append(error_parts(q, s, m))
    return out


def calibrated_trials(argv: list[str]):
    """Parse `[TRIALS] [--tag T] [--opt FIELD=VALUE ...]` and yield, per BROAD trial, (tag, number, session, movement
    mask, calibrate's estimate, its CPU s, offline VQF's quaternions (cached)); shared with h9_velocity_trace."""
    opts, argv = pop_opts(argv)
    tag, argv = pop_value(argv, "--tag", "default")
    options = parse_options(opts)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    CACHE.mkdir(parents=True, exist_ok=True)
    for num, s, mask in iter_broad(select):
        t0 = time.process_time()
        est = calibrate(s, options, allow_weak=True)
        cpu = time.process_time() - t0
        yield tag, num, s, mask, est, cpu, vqf_cached(num, s, CACHE)


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--tag"), max_args=1)
    for tag, num, s, mask, est, cpu, qv in calibrated_trials(argv):
        a, b = error_parts(est.quat, s, mask), error_parts(qv, s, mask)
        sa, sb = (orientation_error(q, s.quat, mask, s.rate).shift_samples for q in (est.quat, qv))
        gate = est.info.get("gyro_map_gate", {})
        print(f"{num} [{tag}] ours {a[0]:.3f} (incl {a[1]:.3f} head {a[2]:.3f}, shift {sa:+.2f})  offVQF {b[0]:.3f} "
              f"(incl {b[1]:.3f} head {b[2]:.3f}, shift {sb:+.2f})  E diag "
              f"{np.round(np.diag(est.calibration.gyro_map) * 100, 3)} %  gate {gate.get('estimated')} "
              f"{cpu:.1f} s CPU", flush=True)
        wo, wv = windows(est.quat, s, mask), windows(qv, s, mask)
        print("   20 s windows tot/incl/head ours-VQF: " + " ".join(
            f"{x[0] - y[0]:+.2f}/{x[1] - y[1]:+.2f}/{x[2] - y[2]:+.2f}" for x, y in zip(wo, wv)))
        np.savez(CACHE / f"{num}_{tag}.npz", quat=est.quat, E=est.calibration.gyro_map,
                 bias_seg=est.info["gyro_bias_segments"], kf=est.info["keyframe_samples"])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
