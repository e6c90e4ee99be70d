"""Session 23 (helper D23): why the real walk's simulations need 16–18 LM iterations (docs/diagnose_body.md).

On the host's base fit (BodyOptions defaults, the diagnosis's single pass) and its simulation A (seed 0, as
`diagnose_body`): the graph cost at the two warm starts of `simulate.fit_simulation` ("solution":
`warm_values`, "generator": `generator_values`), then LM one iteration at a time from each, with gtsam's LM at
the body graph's damping (λ_initial 1e-2, floor 1e-3) and at a smaller one (1e-4, 1e-9; BodyDiagnoseOptions.lm_lambda).

    .venv/bin/python benchmarks/d23_lm_probe.py [--host real_walk] [--duration 25] [--iterations 20]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def trace(graph, x0, order: str, lam0: float, lam_min: float, n: int) -> list:
    """Graph cost after each of n LM iterations (gtsam's LM, one iterate() at a time)."""
    import gtsam
    prm = gtsam.LevenbergMarquardtParams()
    prm.setMaxIterations(1)
    prm.setlambdaInitial(lam0)
    prm.setlambdaLowerBound(lam_min)
    prm.setOrderingType(order.upper())
    opt = gtsam.LevenbergMarquardtOptimizer(graph, x0, prm)
    out = [float(graph.error(x0))]
    for _ in range(n):
        opt.iterate()
        out.append(float(opt.error()))
    return out


def main(argv=None) -> int:
    from benchmarks.d22_long_session import host_session
    from imugraph.diagnose.body.fit import fit_body
    from imugraph.diagnose.body.simulate import fit_options, generator_values, simulate_from_fit, warm_values
    from imugraph.graphs.body import build_problem, full_graph

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--host", default="real_walk")
    p.add_argument("--duration", type=float, default=25.0)
    p.add_argument("--iterations", type=int, default=20)
    a = p.parse_args(argv)
    real = fit_body(host_session(a.host, a.duration, 0))
    print(f"{a.host}: base fit {real.info['iterations']} LM iterations, cost {real.info['cost_initial']:.4g} → "
          f"{real.info['cost_final']:.4g}")
    sim = simulate_from_fit(real, np.random.default_rng(0), "+simA")
    pb = build_problem(sim, fit_options(real))
    g = full_graph(pb)
    starts = {"solution": warm_values(real, pb), "generator": generator_values(sim, real, pb)}
    for name, x0 in starts.items():
        for lam in ((1e-2, 1e-3), (1e-4, 1e-9)):
            c0 = time.process_time()
            tr = trace(g, x0, pb.opts.ordering, lam[0], lam[1], a.iterations)
            print(f"simulation A, start {name}, λ {lam}: cost per iteration "
                  f"{[float(f'{c:.5g}') for c in tr]} ({time.process_time() - c0:.1f} s CPU)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
