"""Session 19 (helper Z, issue 3): does the batch's gyro-map E creep on BROAD 24 (settling step ratio 0.51, then
≈ 0.68 per ML round) come from θ = (D, o, dip) being FREE in the batch's rounds? The stream's end graph, whose E
rounds contract at 0.10–0.22 (stream_gmap), holds θ (the pin θ_n). Per trial, the batch's E rounds with the settling
gate disabled (gyro_map_max_contraction=10, so they run on):

    free      calibration.ml.calibrate as by default (θ free in every round, its weak prior);
    held      the same with θ held at the plain batch's θ̂ (gyro_map=False run): the initial estimate's D, o, dip
              replaced by θ̂ and ml._theta_prior_sigma patched to 1e-6 × (scale, scale, rad) — a diagnostic, the
              library has no option for it;
    D         θ's D held so (o, dip free, their usual weak prior, from θ̂).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/z19_batch_theta_hold.py 24,04,01 [FIELD=VALUE ...]

(FIELD=VALUE: further calibration.ml.Options for both variants, e.g. keyframe_hz=10, the stream's spacing.)

Prints per variant the max|ΔÊ| steps per round (%), their ratios, the RMS vs the optical truth and Ê (%)."""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration import ml  # noqa: E402
from imugraph.calibration.initial import initial_calibration  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402


def _report(name: str, est, s, mask, cpu: float) -> None:
    gate = est.info.get("gyro_map_gate", {})
    steps = [100 * x for x in gate.get("steps", [])]
    ratios = [b / a for a, b in zip(steps, steps[1:]) if a > 0]
    err = orientation_error(est.quat, s.quat, mask, s.rate).rms_deg
    print(f"  {name:5s} steps % {np.round(steps, 4).tolist()} ratios {np.round(ratios, 2).tolist()} RMS {err:.3f}° "
          f"cpu {cpu:.1f} s\n        E % {np.round(100 * np.asarray(est.info['gyro_map']), 3).tolist()}", flush=True)


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=())
    if not argv:
        usage_error("expected TRIALS (e.g. 24,04,01)")
    check_trials(set(argv[0].split(",")))
    opt = parse_options(argv[1:], gyro_map_max_contraction=10.0)
    for num, s, mask in iter_broad(set(argv[0].split(","))):
        print(num)
        c0 = time.process_time()
        _report("free", ml.calibrate(s, opt, allow_weak=True), s, mask, time.process_time() - c0)
        plain = ml.calibrate(s, replace(opt, gyro_map=False), allow_weak=True).calibration
        init = initial_calibration(s)
        init.D, init.o, init.dip_rad = plain.D.copy(), plain.o.copy(), float(np.deg2rad(plain.dip_deg))
        scale = float(np.cbrt(abs(np.linalg.det(plain.D))))
        free_sig = ml._theta_prior_sigma(ml.pack_theta(plain.D, plain.o, np.deg2rad(plain.dip_deg)))
        for name, sig in (("held", np.r_[np.full(12, 1e-6 * scale), 1e-6]),          # D, o, dip held
                          ("D", np.r_[np.full(9, 1e-6 * scale), free_sig[9:]])):     # D held; o, dip free
            c0 = time.process_time()
            with mock.patch.object(ml, "_theta_prior_sigma", lambda *a, _s=sig, **k: _s):
                est = ml.calibrate(s, opt, initial=init)
            _report(name, est, s, mask, time.process_time() - c0)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
