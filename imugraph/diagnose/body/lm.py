"""The diagnosis's LM solves with a smaller damping floor (session 23, option `BodyDiagnoseOptions.lm_lambda`).

`imugraph.graphs.body.optimize` runs gtsam's LM with λ_initial 1e-2 and the floor λ_min 1e-3 (there: the
near-free global translation made the undamped system indefinite). On the real walk (100 Hz) that floor is what
costs the iterations: after 3 iterations the cost is within 30 % of its optimum, then each step shrinks it by
only 1–3 % (the weakly determined directions are damped by λ_min · I), until the relative tolerance 1e-3 stops
it — each simulation 16–18 iterations (docs/diagnose_body.md "Session 23, helper D23"). With λ_initial 1e-4
and λ_min 1e-9 the same graph from the same start reaches a LOWER cost in 4–5 iterations (simulation A of the
real walk: 64.68 after 5 against 65.16 after 18 with the floor). The recording's own base fit is not helped
(18–21 iterations either way: its slow tail stays at λ 1e-4, a nonlinear one). The graph, its start and its
stopping rule are unchanged: only the damping, i.e. the path to the optimum.

    (JᵀJ + λ I) δ = −Jᵀ r,   λ ← λ/10 after an accepted step, ≥ λ_min;   ×10 after a rejected one   (LM)
"""

from __future__ import annotations

import time


def lm_optimize(pb, graph, values, lm: tuple | None = None) -> tuple:
    """(values, info) of LM on the body graph: `graphs.body.optimize` when lm is None (or the problem needs the
    Python loop of hinge factors), else gtsam's LM with (λ_initial, λ_min) = lm, the problem's max_iterations,
    relative tolerance and ordering (LM above); info as optimize's plus "lm"."""
    import gtsam

    from imugraph.graphs.body import optimize

    if lm is None or (pb.bRs_fixed is not None and pb.opts.hinges):
        return optimize(pb, graph, values)
    t0 = time.perf_counter()
    prm = gtsam.LevenbergMarquardtParams()
    prm.setMaxIterations(pb.opts.max_iterations)
    prm.setRelativeErrorTol(pb.opts.relative_tol)
    prm.setOrderingType(pb.opts.ordering.upper())
    prm.setlambdaInitial(float(lm[0]))
    prm.setlambdaLowerBound(float(lm[1]))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, prm)
    x = opt.optimize()
    return x, {"iterations": int(opt.iterations()), "cost_initial": float(graph.error(values)),
               "cost_final": float(graph.error(x)), "seconds": time.perf_counter() - t0,
               "lm": (float(lm[0]), float(lm[1]))}
