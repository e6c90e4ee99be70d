"""Task E (session 16): does saturation's (C1'') estimate of the censored gyro values recover the TRUE
rate, or only agree with the keyframes? Simulations (truth known, used only to measure) clipped so that
≈ 2 % of samples exceed the rail; the error of each keyframe interval's censored area Σ ω dt (summed
squares over intervals, rad²) for the quadratic reconstruction alone and for (C1'') against the keyframes
of the base fit of the clipped data, and of the base model refitted to the quadratic reconstruction (the
refit's round 1).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/e5_censored_area.py --seeds 3,5,6
"""
from __future__ import annotations

import argparse

import numpy as np

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import saturation as sat
from imugraph.diagnose.effects.base import replace_session
from imugraph.diagnose.fit import base_options, fit_base, fit_simulation
from imugraph.diagnose.refit import on_session


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="3,5,6")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--frac", type=float, default=0.02)
    a = ap.parse_args()
    for seed in [int(x) for x in a.seeds.split(",")]:
        s = simulated_session(seed, a.duration, a.rate)
        level = float(np.quantile(np.max(np.abs(s.gyr), axis=1), 1.0 - a.frac))
        clipped = replace_session(s, gyr=np.clip(s.gyr, -level, level))
        fit = fit_base(clipped, base_options(5.0))
        rails = sat.find_rails(clipped.gyr, np.ones(fit.n, bool))
        y_q = sat.reconstruct_peaks(clipped.t, clipped.gyr, rails)
        refit = on_session(fit_simulation(replace_session(clipped, gyr=y_q), fit), clipped)
        k_of = sat._intervals(fit)
        hit = np.zeros(fit.n, bool)
        for ax, _sg, lv in rails:
            hit |= sat.on_rail(clipped.gyr[:, ax], lv)

        def err(y):
            return sum(float(np.sum(((y - s.gyr)[m] * clipped.dt[m, None]).sum(0) ** 2))
                       for m in (hit & (k_of == k) for k in np.unique(k_of[hit])))

        print(f"seed {seed}: {hit.sum()} clipped samples in {len(np.unique(k_of[hit]))} intervals; area error "
              f"quadratic {err(y_q):.3g}, (C1'') base keyframes {err(sat.censored_values(fit, y_q, rails)):.3g}, "
              f"(C1'') refit keyframes {err(sat.censored_values(refit, y_q, rails)):.3g} rad²")


if __name__ == "__main__":
    main()
