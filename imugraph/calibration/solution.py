"""Read-outs of a solved single-IMU calibration problem (imugraph.calibration.ml): the marginal covariances
of θ and the gyro bias, and the per-sample whitened residuals of each channel."""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.theta import THETA_DIM
from imugraph.graphs.single_imu import Problem
from imugraph.io.session import Session


def marginal_covariances(prob: Problem, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
    """Marginal covariances of θ (13×13) and the gyro bias (3×3) at the solution."""
    gfg = prob.graph.linearize(values)
    for b in prob.blocks:
        gfg.push_back(b.linearize(values))
    others = [k for k in prob.ordering_keys if k not in (keys.CALIB, keys.BIAS)]
    bn = gfg.marginalMultifrontalBayesNet(gtsam.Ordering([keys.CALIB, keys.BIAS]), gtsam.Ordering(others))
    marg = gtsam.GaussianFactorGraph()
    marg.push_back(bn)
    info = marg.augmentedHessian(gtsam.Ordering([keys.CALIB, keys.BIAS]))[:-1, :-1]
    cov = np.linalg.inv(info)
    return cov[:THETA_DIM, :THETA_DIM], cov[THETA_DIM:, THETA_DIM:]


def per_sample_residuals(prob: Problem, nRk: np.ndarray, theta: np.ndarray, session: Session) -> dict:
    """Whitened residuals per channel as (N, 3) arrays with NaN rows where a channel has no sample."""
    out = {}
    res = prob.block.residuals(nRk, theta)
    for name, src in (("acc", session.acc), ("mag", session.mag)):
        if name in res:
            full = np.full((session.n, 3), np.nan)
            full[np.all(np.isfinite(src), axis=1)] = res[name]
            out[name] = full
    return out
