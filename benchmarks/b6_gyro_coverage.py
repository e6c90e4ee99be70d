"""B6 (issue 2c): what the gyro-map coverage gate sees on each BROAD trial — turns of rotation inside the
keyframe intervals where the accelerometer reads gravity alone (| |b_acc| − g | < 2 m/s²), in total and
per body axis (∫|ω_i| dt / 2π), and the fraction of such intervals.

    .venv/bin/python benchmarks/b6_gyro_coverage.py [TRIALS]

E's column i (the error of rate axis i) is excited only by rotation about body axis i, so the per-axis
turns say which columns the data can inform (the prior σ_e holds the others at 0). g is the median
|b_acc| at rest as calibrate uses it (initial_calibration's rest mask; median of all samples without one).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, print_table  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.gyro_map import clean_intervals  # noqa: E402
from imugraph.calibration.initial import initial_calibration, weak_initial  # noqa: E402
from imugraph.calibration.ml import Options, gravity_from, stride_for  # noqa: E402
from imugraph.errors import CalibrationError  # noqa: E402
from imugraph.factors.gyro import keyframe_layout  # noqa: E402


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=(), max_args=1)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    opt, rows = Options(), []
    for num, s, _ in iter_broad(select):
        try:
            init = initial_calibration(s)
        except CalibrationError as exc:
            init = weak_initial(s, str(exc))
        g = gravity_from(s, getattr(init, "rest", None))
        kf, skf = keyframe_layout(s.n, stride_for(s, opt.keyframe_hz))
        clean = clean_intervals(s.acc, g, skf, len(kf) - 1, opt.gyro_map_acc_tol)
        ok = np.r_[clean, False][skf]
        per_axis = np.sum(np.abs(s.gyr[ok]) * s.dt[ok, None], axis=0) / (2 * np.pi)
        total = float(np.sum(np.linalg.norm(s.gyr[ok], axis=1) * s.dt[ok]) / (2 * np.pi))
        net_z = float(np.sum(s.gyr[ok, 2] * s.dt[ok]) / (2 * np.pi))
        rows.append({"trial": s.name[:30], "clean_fraction": round(float(clean.mean()), 2),
                     "clean_turns": round(total, 1), "turns_x": round(float(per_axis[0]), 1),
                     "turns_y": round(float(per_axis[1]), 1), "turns_z": round(float(per_axis[2]), 1),
                     "net_turns_z": round(net_z, 1), "gate_passed": total >= opt.gyro_map_min_turns})
    print_table(rows, list(rows[0].keys()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
