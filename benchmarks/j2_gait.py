"""Task J (issue 2c): the bounded-position selection on a real walk — gaittoolbox S02-Trial-Walk-1 (7 Xsens MTw,
100 Hz, 25 s: ≈ 10 s standing, then walking across the lab and back).

    .venv/bin/python benchmarks/j2_gait.py [SEGMENTS] --variant "position_select=(1e4,1.0,0.3,0.1)" ...

Each sensor is calibrated and smoothed on its own (imugraph.calibration.ml.calibrate, allow_weak: 25 s do not
cover every rotation). No Vicon alignment here: each variant is scored against (a) the MTw's own onboard
orientation (Xsens' filter, Session.quat: a reference, not the truth; RMS total / inclination / heading error with
the best constant heading removed, over the whole recording) and (b) the defaults' own result (RMS angle between
the two). Per sensor and variant: the σ_p chosen (None = no position state). The defaults ("base") run first.
Writes bench_out/j2_gait.json.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, parse_options, parse_variants  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.config import data_dir  # noqa: E402
from imugraph.geometry import quat_angle  # noqa: E402
from imugraph.io.gaittoolbox import read_gaittoolbox  # noqa: E402

SEGMENTS = ("Pelvis", "LeftFoot", "RightFoot", "LeftLowerLeg", "RightLowerLeg")


def _angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    """RMS rotation angle (°) between two (N, 4) w, x, y, z quaternion sequences."""
    return float(np.rad2deg(np.sqrt(np.mean(quat_angle(q1, q2) ** 2))))


def main(argv: list[str]) -> int:
    if {"-h", "--help"} & set(argv):
        print(__doc__)
        return 0
    variants, rest = parse_variants(argv)
    segs = rest[0].split(",") if rest else list(SEGMENTS)
    root = data_dir() / "gaittoolbox" / "rawimu"
    if not root.is_dir():
        print(f"{root} absent")
        return 2
    body = read_gaittoolbox(root, "S02-Trial-Walk-1")
    unknown = [seg for seg in segs if seg not in body.sensors]
    if unknown:
        print(f"j2_gait: error: SEGMENTS: found {', '.join(unknown)}; expected some of {', '.join(body.sensors)}")
        return 2
    rows = []
    for seg in segs:
        s = body.sensors[seg]
        mask = np.ones(s.n, bool)
        row, quats = {"segment": seg}, {}
        for name, opts in variants.items():
            t0 = time.process_time()
            est = calibrate(s, parse_options(opts), allow_weak=True)
            quats[name] = est.quat
            row[name] = error_parts(est.quat, s, mask)
            row[name + "_cpu"] = time.process_time() - t0
            row[name + "_sigma_p"] = est.info.get("position_sigma")
            row[name + "_vs_base"] = _angle_deg(est.quat, quats["base"])
        rows.append(row)
        print(f"{seg} | " + " | ".join(
            f"{n} vs MTw {row[n][0]:.2f} (i {row[n][1]:.2f} h {row[n][2]:.2f}), vs base {row[n + '_vs_base']:.3f}, "
            f"σp {row[n + '_sigma_p']}, {row[n + '_cpu']:.1f} s" for n in variants), flush=True)
    for n in variants:
        print(f"[{n}] inclination vs MTw mean {np.mean([r[n][1] for r in rows]):.3f}°; largest change vs base "
              f"{max(r[n + '_vs_base'] for r in rows):.3f}°; σ_p chosen {[r[n + '_sigma_p'] for r in rows]}")
    write_json("j2_gait.json", {"variants": variants, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
