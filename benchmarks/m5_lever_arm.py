"""Benchmark (issue 5, §S17-H): is a constant accelerometer bias identifiable on a hand-held crop once the
rotation's own lever-arm acceleration is modelled?

For each host crop (the harness' most-moving 60 s of BROAD trials), clean and with a known accelerometer bias
injected (accelerometer_bias.inject, fixed direction and size), fit the base model and regress the acc
residual (R2) on the trajectory fixed:

    r_acc,j ≈ δ_a + δg R̂_jᵀ ẑ                                       (the effect's fit (A1), 4 parameters)
    r_acc,j ≈ δ_a + δg R̂_jᵀ ẑ + ([ω̂_j]×² + [α̂_j]×) r                 (+ a body-fixed lever arm r, (LA1))

and print δ_a(injected) − δ_a(clean) against the injected bias, and |δ_a(clean)| (the host's apparent bias).

    .venv/bin/python benchmarks/m5_lever_arm.py --trials 01,04,06,07 --bias 0.25
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def lever_columns(fit, smooth_s: float = 0.1) -> np.ndarray:
    """(N, 3, 3): K_j = [ω̂_j]×² + [α̂_j]× so that K_j r is the rotation's acceleration at lever arm r (LA1)."""
    from imugraph.diagnose.effects.base import smooth
    from imugraph.geometry import skew

    n = max(1, int(round(smooth_s * fit.session.rate)))
    w = smooth(np.asarray(fit.b_omega, float), n)
    a = smooth(np.gradient(w, fit.session.t, axis=0), n)
    W = skew(w)
    return W @ W + skew(a)


def regress(fit, lever: bool) -> np.ndarray:
    """θ = (δ_a, δg[, r]) by whitened least squares on all finite rows."""
    r = fit.residuals["acc"]
    ok = np.all(np.isfinite(r), axis=1)
    cols = [np.broadcast_to(np.eye(3), (fit.n, 3, 3)), fit.nRb[:, 2, :][:, :, None]]
    if lever:
        K = lever_columns(fit)
        ok &= np.all(np.isfinite(K), axis=(1, 2))
        cols.append(K)
    J = np.concatenate(cols, axis=2)
    w = 1.0 / np.asarray(fit.sigma["acc"], float)
    A = (J[ok] * w[None, :, None]).reshape(-1, J.shape[2])
    return np.linalg.lstsq(A, (r[ok] * w).reshape(-1), rcond=None)[0]


def main(argv=None) -> int:
    from imugraph.diagnose.bench import broad_sessions
    from imugraph.diagnose.effects.accelerometer_bias import EFFECT
    from imugraph.diagnose.fit import fit_base

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default="01,04,06,07")
    p.add_argument("--bias", type=float, default=0.25, help="|δ_a| injected, m/s²")
    p.add_argument("--seed", type=int, default=0, help="seed of the bias direction")
    p.add_argument("--duration", type=float, default=60.0)
    a = p.parse_args(argv)
    for s in broad_sessions([t.strip() for t in a.trials.split(",")], a.duration):
        inj, truth = EFFECT.inject(s, np.random.default_rng(a.seed), strength=a.bias)
        b_true = np.asarray(truth["params"]["bias_ms2"])
        f0, f1 = fit_base(s), fit_base(inj)
        for lever in (False, True):
            t0, t1 = regress(f0, lever), regress(f1, lever)
            d = t1[:3] - t0[:3]
            extra = f" r_clean {np.round(t0[4:7], 3)} m" if lever else ""
            print(f"{s.name[:2]} lever={int(lever)}: |δa clean| {np.linalg.norm(t0[:3]):.3f}  δa(inj)−δa(clean) "
                  f"{np.round(d, 3)} vs injected {np.round(b_true, 3)} (error {np.linalg.norm(d - b_true):.3f})"
                  + extra, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
