"""Benchmark (issue 5, §S17-H): the floor E0 of the joint gyro fit's excess cost (J6) — nominal against measured.

(J6) S = gain / Σ_c max(0, C_base,c/n − E0_c) with E0_c = ½ Σ_axis (σ_c/σ_row)² the cost per row the model's
own noise would give (effects/joint.py `heldout_cost`). For harness cases (replayed: same draw as
benchmarks/diagnose_harness.py --seed S --cases ...) print per channel: E0 nominal, the base cost per row
of the real crop (J1 at p = 0, all rows), and the same for a simulation from the fit (the data the model
itself produces, fitted the same way: what "no excess" actually costs).

    .venv/bin/python benchmarks/m5_own_floor.py --seed 2 --cases 006,019,022
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def cost_per_row(fit_sig, r: np.ndarray) -> float:
    from imugraph.diagnose.effects.joint import _cost

    ok = np.all(np.isfinite(r), axis=1)
    return _cost(r[ok] / fit_sig) / max(int(ok.sum()), 1)


def main(argv=None) -> int:
    from imugraph.diagnose.bench import add_arguments, harness_run, harness_sessions
    from imugraph.diagnose.effects import joint
    from imugraph.diagnose.fit import base_options, fit_base, fit_simulation, simulate_from_fit

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    a = p.parse_args(argv)
    sessions = harness_sessions(a)

    def fn(session):
        real = fit_base(session, base_options(5.0))
        rng = np.random.default_rng(0)
        simA = fit_simulation(simulate_from_fit(real, rng, name="A"), real)
        sig = joint._sigmas(real)
        z = np.zeros((real.n, 3))
        r_real = joint.null_residuals(real, z)
        r_sim = joint.null_residuals(simA, z)
        for c in ("gyr", "acc", "mag"):
            e0 = 0.5 * float(np.sum((np.asarray(real.sigma[c], float) / sig[c]) ** 2))
            print(f"  {session.name[:28]:<28} {c}: E0 nominal {e0:.4f}  real J1(p=0) {cost_per_row(sig[c], r_real[c]):.4f}"
                  f"  real calibrate {cost_per_row(sig[c], real.residuals[c]):.4f}"
                  f"  sim J1(p=0) {cost_per_row(sig[c], r_sim[c]):.4f}  sim calibrate {cost_per_row(sig[c], simA.residuals[c]):.4f}",
                  flush=True)
        return {"verdict": "none", "effects": []}

    harness_run(a, sessions, fn)
    return 0


if __name__ == "__main__":
    sys.exit(main())
