"""Several EM steps of the velocity process per ML round, at the round's orientations (Options.velocity_em_inner).

The ML loop takes one EM step of the AR(2) process per round (calibration/velocity_ar2.py): E-step = the round's
solve (means) plus the chain's posterior covariances, M-step = `fit_ar2`. Where the process moves far from its
start ("free_ar2" on BROAD 02: σ_v 0.5 → 0.043 m/s) that is one graph solve per EM step, and EM's linear
convergence needs more rounds than the loop's other quantities (02, 07: 7 rounds, still moving 0.015 per round in
a_1 when the loop's settling test stops it).

With the orientations (and the accelerometer increments' robust weights) held, the velocity chain is linear and
Gaussian (velocity_process.chain_bands: banded precision Λ per nav axis), so its E-step needs no graph solve:

    Λ m = η,   η_k = a_{k−1} c_{k−1} − a_k c_k,   c_k = R_k Δv_k + n_grav Δt_k,   a_k = w_k / σ_dv,k²           (1)

(the minimiser of ½ Σ_k a_k |v_{k+1} − v_k − c_k|² + the process and rest priors; imugraph.factors.velocity), and
the covariances by Takahashi's recursion as before. This module repeats E-step (1) and the M-step at fixed
orientations up to `iters` times (until the process moves less than `tol`), i.e. it takes the round's process
to (near) the maximiser of the velocity chain's marginal likelihood at those orientations; the rounds then only
have to settle the coupling between orientations and process. Not with an accelerometer bias in the state.
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.linalg import solveh_banded

from imugraph.calibration.velocity_process import chain_bands
from imugraph.factors.velocity import velocity_model


def increment_rhs(block, nRk: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(K, 3) right-hand side of the velocity chain's normal equations: the robust-weighted accelerometer
    increments at orientations nRk (weights at states s)."""
    K = block.n_keyframes
    c = -velocity_model(nRk, np.zeros((K, 3)), block.dv, block.dt_k, block.g, None, None)[0]
    _, _, w, *_ = block.terms(nRk, s)
    a = (w / block.sigma_dv**2)[:, None]
    eta = np.zeros((K, 3))
    eta[:-1] -= a * c
    eta[1:] += a * c
    return eta


def posterior_mean(block, nRk: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(K, 3) velocities minimising the chain's cost at orientations nRk, eq. (1), robust weights at states s."""
    eta = increment_rhs(block, nRk, s)
    ab = chain_bands(block, nRk, s)
    return np.stack([solveh_banded(ab[:, :, i], eta[:, i], lower=True) for i in range(3)], axis=1)


def _params(vel_state: dict) -> tuple | None:
    ar2 = vel_state.get("ar2")
    return None if ar2 is None else (float(ar2[0]), float(ar2[1]), float(ar2[2]))


def em_at_orientations(vel_state: dict, block, nRk: np.ndarray, step, iters: int, tol: float = 1e-3) -> float:
    """`step(vel_state, block)` (one EM M-step of the AR(2) process from vel_state["s"], returning its change)
    repeated with E-step (1) in between, at most `iters` times or until the change < tol. vel_state["s"] ends
    at the posterior means under the process before the last M-step (the E-step precedes each M-step; the next
    round's solve gives the means under the final one). Returns the change of the process
    over the whole call (|Δa_1|, |Δa_2|, |Δ ln q|; the first step's own change when there was no AR(2) before)."""
    if iters <= 1 or block.B is not None:
        return step(vel_state, block)
    start = _params(vel_state)
    first = step(vel_state, block)
    b = copy.copy(block)
    for _ in range(iters - 1):
        if vel_state.get("ar2") is None:          # chain too short for the AR(2) step
            break
        b.ar2 = vel_state["ar2"]
        s = np.asarray(vel_state["s"], float).copy()
        s[:, :3] = posterior_mean(b, nRk, s)
        vel_state["s"] = s
        if step(vel_state, b) < tol:
            break
    end = _params(vel_state)
    if start is None or end is None:
        return first
    return float(max(abs(end[0] - start[0]), abs(end[1] - start[1]), abs(np.log(end[2] / start[2]))))
