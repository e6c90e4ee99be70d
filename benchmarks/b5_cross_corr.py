"""Benchmark (issue 5, S16): the cross-channel statistic (G4)/(G4') of chosen harness cases, without a diagnosis.

Rebuilds the harness' cases exactly as `benchmarks/diagnose_harness.py` draws them (same sessions, seed and
random sequence), fits the base model to each selected case and to two simulations from that fit (A, B, as
`imugraph.diagnose.run` does), and prints per channel (acc, mag) and axis the correlation (G4) — or with
--form cov the covariance in whitened units (G4') — of the whitened residual with the model's motion
derivative ḣ = (h − o) × ω̂ (imugraph/diagnose/gap.py), for the case, simulation A and simulation B.

    .venv/bin/python benchmarks/b5_cross_corr.py --seed 0 --cases 008,021
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    from imugraph.diagnose import gap as G
    from imugraph.diagnose.bench import broad_sessions, simulated_session
    from imugraph.diagnose.effects import EFFECTS
    from imugraph.diagnose.fit import base_options, fit_base, fit_simulation, simulate_from_fit
    from imugraph.diagnose.harness import run_harness

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cases", default="008,021", help="harness case ids (clean hosts after the 16 injected)")
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--form", choices=("corr", "cov"), default="corr")
    args = p.parse_args(argv)
    sessions = broad_sessions(["01", "02", "04", "06", "07"], args.duration)
    sessions += [simulated_session(args.seed * 100 + i, args.duration, 285.714) for i in range(2)]

    def stat(fit, sigma):
        u = G.motion_derivatives(fit)
        return {c: G.motion_correlation(fit.residuals[c] / sigma[c], u[c], np.ones(fit.n, bool), args.form)
                for c in ("acc", "mag")}

    def fn(session):
        real = fit_base(session, base_options(5.0))
        rng = np.random.default_rng(0)                      # DiagnoseOptions.seed = 0, as the diagnosis
        a = fit_simulation(simulate_from_fit(real, rng), real)
        b = fit_simulation(simulate_from_fit(real, rng), real)
        for name, f in (("case", real), ("sim A", a), ("sim B", b)):
            s = stat(f, real.sigma)
            print(f"{session.name} {name:5s} " + "  ".join(
                f"{c} " + "/".join(f"{v:+.3f}" for v in s[c]) for c in ("acc", "mag")), flush=True)
        return {"verdict": "none", "effects": []}

    run_harness(sessions, list(EFFECTS), 2, np.random.default_rng(args.seed), diagnose_fn=fn,
                only=[c.strip() for c in args.cases.split(",") if c.strip()])
    return 0


if __name__ == "__main__":
    sys.exit(main())
