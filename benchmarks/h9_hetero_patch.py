"""H9 (issue 2c): the two graph-side changes mode "hetero_ar2" (calibration/velocity_hetero.py) needs, applied at
run time for measurement only — the proposed patches to imugraph/factors/velocity.py (ar2_residuals) and
imugraph/graphs/velocity_block.py (_ar2_factors), which helper C does not own: each AR(2) innovation m whitened by
√(q h_m) instead of √q when q carries a per-innovation scale h (velocity_hetero.HeteroQ); a plain q is unchanged.

    .venv/bin/python benchmarks/h9_hetero_patch.py [broad_published.py arguments]
    (e.g. --opt estimate_velocity_process="'hetero_ar2'"): runs benchmarks/broad_published.py with the patch;
    other scripts: `import benchmarks.h9_hetero_patch as p; p.install()` first.
"""

from __future__ import annotations

import sys
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import imugraph.factors.velocity as fv  # noqa: E402
import imugraph.graphs.velocity_block as vbm  # noqa: E402

_plain_residuals = fv.ar2_residuals


def ar2_residuals(v: np.ndarray, a1: float, a2: float, q) -> np.ndarray:
    """fv.ar2_residuals, innovation rows divided by √h_m when q carries h (proposed patch)."""
    r = _plain_residuals(v, a1, a2, q)
    h = getattr(q, "h", None)
    if h is not None:
        r[2:] = r[2:] / np.sqrt(np.asarray(h, float))[:, None]
    return r


def _ar2_factors(self, gfg: gtsam.GaussianFactorGraph, s: np.ndarray, vk: list) -> None:
    """VelocityBlock._ar2_factors with innovation k−1 scaled by 1/√h (proposed patch)."""
    a1, a2, q = self.ar2
    r = ar2_residuals(s[:, :3], a1, a2, q)
    h = getattr(q, "h", None)
    A = [np.zeros((3, self.state_dim)) for _ in range(3)]
    for block, c in zip(A, (-a2, -a1, 1.0)):
        block[:, :3] = c * np.eye(3) / np.sqrt(q)
    unit3 = gtsam.noiseModel.Unit.Create(3)
    for k in range(1, self.n_keyframes - 1):
        sc = 1.0 if h is None else 1.0 / np.sqrt(h[k - 1])
        gfg.push_back(gtsam.JacobianFactor(vk[k - 1], A[0] * sc, vk[k], A[1] * sc, vk[k + 1], A[2] * sc,
                                           -r[k + 1], unit3))


def install() -> None:
    fv.ar2_residuals = ar2_residuals
    vbm.ar2_residuals = ar2_residuals
    vbm.VelocityBlock._ar2_factors = _ar2_factors
    vbm.VelocityBlock.SUPPORTS_HETERO_Q = True      # velocity_hetero.interval_intensity checks this before any solve


if __name__ == "__main__":
    install()
    from benchmarks.broad_published import main
    sys.exit(main(sys.argv[1:]))
