"""H9 (issue 2c): the velocity process per ML round and the error, per trial and Options variant.

    .venv/bin/python benchmarks/h9_velocity_trace.py 02,07 --tag free --opt estimate_velocity_process="'free_ar2'"

Prints per trial: total / inclination / heading RMS error (deg; offline VQF's beside it, cached), CPU seconds,
and per ML round the AR(2) coefficients (a_1, a_2, q), √γ_0 (σ_v) and τ_v; keeps bench_out/h4/{trial}_{tag}.npz
(the same layout as h4_decompose.py, so h4_error_split.py reads it).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts  # noqa: E402
from benchmarks.h4_decompose import CACHE, calibrated_trials  # noqa: E402
from benchmarks._usage import exit_on_help  # noqa: E402


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--tag"), max_args=1)
    if any("hetero_ar2" in a for a in argv):     # the graph-side patch it needs (benchmarks/h9_hetero_patch.py)
        from benchmarks.h9_hetero_patch import install
        install()
    for tag, num, s, mask, est, cpu, qv in calibrated_trials(argv):
        a, b = error_parts(est.quat, s, mask), error_parts(qv, s, mask)
        print(f"{num} [{tag}] ours {a[0]:.3f} (incl {a[1]:.3f} head {a[2]:.3f})  offVQF {b[0]:.3f} "
              f"(incl {b[1]:.3f} head {b[2]:.3f})  {cpu:.2f} s CPU, {len(est.info['history'])} rounds", flush=True)
        gate = est.info.get("gyro_map_gate", {})
        print(f"   gyro map: estimated {gate.get('estimated')}, contraction {gate.get('contraction')}, E diag "
              f"{np.round(np.diag(est.calibration.gyro_map) * 100, 3).tolist()} %; reason {gate.get('reason')}")
        for h in est.info["history"]:
            ar2 = h.get("velocity_ar2")
            sel = h.get("velocity_lambda")
            print(f"   round {h['outer']}: ar2 {np.round(ar2, 4).tolist() if ar2 else None}  σ_v "
                  f"{np.round(h.get('velocity_sigma', np.nan), 4)}  τ_v {np.round(h.get('velocity_tau', np.nan), 3)}"
                  + (f"  λ {sel:.3g}" if sel is not None else ""))
        np.savez(CACHE / f"{num}_{tag}.npz", quat=est.quat, E=est.calibration.gyro_map,
                 bias_seg=est.info["gyro_bias_segments"], kf=est.info["keyframe_samples"],
                 velocity=est.info["velocity"])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
