"""C1 (issue 2c): inclination of imugraph vs offline VQF on chosen BROAD trials under Options variants.

    .venv/bin/python benchmarks/c1_ablate.py 30,36,02 [VARIANT ...]

Prints per trial and variant: total / inclination / heading RMS (deg) and the mean nav-frame tilt error.
Variants are named in VARIANTS below (default: all).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.b1_try import nav_tilt_mean, vqf_cached  # noqa: E402
from benchmarks.common import error_parts, iter_broad  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import Options, calibrate  # noqa: E402
from imugraph.factors.robust import Kernel  # noqa: E402

BASE = Options()
VARIANTS = {
    "base": {},
    "kappa0": {"acc_rate_error": 0.0},
    "kappa.003": {"acc_rate_error": 0.003},
    "kappa.03": {"acc_rate_error": 0.03},
    "kappa.1": {"acc_rate_error": 0.1},
    "kappa.3": {"acc_rate_error": 0.3},
    "zupt": {"zero_velocity_at_rest": True},
    "zupt_k.1": {"zero_velocity_at_rest": True, "acc_rate_error": 0.1},
    "zupt_k.3": {"zero_velocity_at_rest": True, "acc_rate_error": 0.3},
    "acc_quad": {"acc_kernel": Kernel("quadratic")},
    "vsig.2": {"velocity_sigma": 0.2},
    "vsig1": {"velocity_sigma": 1.0},
    "vtau.5": {"velocity_tau": 0.5},
    "vtau5": {"velocity_tau": 5.0},
    "nofield": {"field_sigma": None},
    "nowin": {"disturbance_windows": False},
    "nogmap": {"gyro_map": False},
    "accbias": {"acc_bias": True},
    "accnoise": {"linear_acceleration": "noise"},
    "headonly": {"heading_only_orientation": True},
    "lead.5": {"acc_lead_samples": 0.5},
    "lead1": {"acc_lead_samples": 1.0},
    "lead1_zupt": {"acc_lead_samples": 1.0, "zero_velocity_at_rest": True},
}


def main(argv):
    exit_on_help(__doc__, argv, flags=())
    select = set(argv[0].split(",")) if argv else None
    names = argv[1:] or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        usage_error(f"unknown variant(s) {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    check_trials(select)
    for num, s, mask in iter_broad(select):
        qv = vqf_cached(num, s)
        v = error_parts(qv, s, mask)
        mv, _ = nav_tilt_mean(qv, s, mask)
        print(f"{num} offVQF {v[0]:.3f} incl {v[1]:.2f} head {v[2]:.2f} tilt {mv.round(2)}", flush=True)
        for name in names:
            opt = replace(BASE, **VARIANTS[name])
            est = calibrate(s, opt, allow_weak=True)
            o = error_parts(est.quat, s, mask)
            m, _ = nav_tilt_mean(est.quat, s, mask)
            print(f"{num} {name:10s} {o[0]:.3f} incl {o[1]:.2f} head {o[2]:.2f} tilt {m.round(2)} "
                  f"g {est.info['g']:.4f}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
