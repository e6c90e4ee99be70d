"""A velocity process whose innovation variance follows the measured motion intensity (mode "hetero_ar2").

The AR(2) process of calibration/velocity_ar2.py is stationary: one innovation variance q for the whole
recording. A hand-held sensor is not: it rests, turns slowly, then shakes. On the BROAD optical velocities
(evaluation only, benchmarks/h9_velocity_trace.py notes) the squared AR(2) innovations correlate +0.2 … +0.6
with the interval's mean (|b_acc| − g)², and one q is then too tight in the vigorous windows (the tilt absorbs
the motion: BROAD 15/16) and too loose in the calm ones (the tilt wanders: BROAD 02 with the "bounded" floor).

Model, per nav axis, innovation m = 0 … K−3 (it predicts v_{m+2} across keyframe interval m+1):

    v_{m+2} = a_1 v_{m+1} + a_2 v_m + w_m,   w_m ~ N(0, q h_m),   h_m = 1 + λ u_{m+1} / ū            (1)

with u_k = mean over interval k of | |b_acc,j| − g | — the sensor's own data, no truth — and ū its mean over
the intervals. λ ≥ 0 is a third parameter of the process (λ = 0: the stationary AR(2) process). The EM step
(Shumway & Stoffer 1982, as in velocity_ar2) maximises the expected complete-data log-likelihood

    −log L(a, q, λ) = (N/2) ln q + (n/2) Σ_m ln h_m(λ) + f_λ(a) / (2q),
    f_λ(a) = Σ_m E(v_{m+2} − a_1 v_{m+1} − a_2 v_m)² / h_m(λ),     N = n (K − 2), n = 3 axes              (2)

for fixed λ exactly as the stationary M-step with 1/h_m-weighted moments (`velocity_ar2.fit_ar2`), and λ by a
search over a log grid. The stationary start (v_0, v_1) keeps the base q. The E-step's posterior covariances
come from the chain's banded precision with the per-innovation variances q h_m (velocity_process.chain_bands).

Measured (H9, BROAD, benchmarks/h9_hetero_patch.py --opt estimate_velocity_process="'hetero_ar2'", 12 trials
before it was stopped): 02 0.473 → 0.396°, but 07 0.506 → 0.589°, 06 0.557 → 0.716° (heading 0.437 → 0.582°),
01 0.767 → 1.201° (the gyro map's settling gate fails, contraction 0.61: the plain model's result), 15/16
0.887°/0.399° (their excess slow tilt untouched); with the squared deviation as u, λ ran to 420 (02) and the
grid's edge 1000 (07), 07 0.818°. Not adopted.
Needs the graph-side patch (benchmarks/h9_hetero_patch.py); without it `update_hetero` refuses to run.

The per-innovation scale travels with q itself: `HeteroQ`, a float (the base q, so every consumer of a scalar
q — stationary start, first-order equivalent, the stream — reads q) carrying the array h.
"""

from __future__ import annotations

import numpy as np

from imugraph.calibration.velocity_ar2 import fit_ar2
from imugraph.factors.velocity import ar2_stationary

LAMBDA_GRID = np.r_[0.0, np.geomspace(0.03, 1000.0, 13)]


class HeteroQ(float):
    """The base innovation variance q (a float) with the per-innovation scale h (K−2,) of eq. (1)."""

    def __new__(cls, q: float, h: np.ndarray, lam: float = 0.0):
        obj = super().__new__(cls, float(q))
        obj.h = np.asarray(h, float)
        obj.lam = float(lam)
        return obj


def innovation_scale(q) -> np.ndarray | None:
    """h (K−2,) of a HeteroQ, None for a plain q."""
    return getattr(q, "h", None)


def calibration_intensity(acc: np.ndarray, g: float, sample_kf: np.ndarray, n_keyframes: int) -> np.ndarray:
    """interval_intensity for ml.calibrate, refusing before any solve when the graph cannot whiten per step."""
    from imugraph.graphs.velocity_block import VelocityBlock

    if not getattr(VelocityBlock, "SUPPORTS_HETERO_Q", False):
        raise ValueError("Options.estimate_velocity_process: found 'hetero_ar2', expected a mode the graph supports "
                         "('hetero_ar2' needs the graph patch of benchmarks/h9_hetero_patch.install(); not adopted)")
    return interval_intensity(acc, g, sample_kf, n_keyframes)


def interval_intensity(acc: np.ndarray, g: float, sample_kf: np.ndarray, n_keyframes: int) -> np.ndarray:
    """u_k (K−1,) of eq. (1): mean over the samples of keyframe interval k of | |b_acc| − g |, m/s² (the square
    instead: BROAD 02 0.403°, 07 0.574° with λ held ≤ 10; λ ran to the grid's edge without the cap)."""
    dev = np.abs(np.linalg.norm(np.asarray(acc, float), axis=1) - float(g))
    ok = np.isfinite(dev)
    idx = np.asarray(sample_kf)[ok]
    n = np.bincount(idx, minlength=n_keyframes)
    s = np.bincount(idx, weights=dev[ok], minlength=n_keyframes)
    u = s / np.maximum(n, 1)
    return u[:n_keyframes - 1]


def scale_for(u: np.ndarray, lam: float) -> np.ndarray:
    """h_m (K−2,) of eq. (1) from the interval intensities u (K−1,)."""
    u = np.asarray(u, float)
    mean = float(np.mean(u)) if np.mean(u) > 0 else 1.0
    return 1.0 + float(lam) * u[1:] / mean


def weighted_terms(E: list[np.ndarray], h: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """`velocity_ar2.ar2_objective_terms` with innovation m weighted by 1/h_m (eq. 2)."""
    E0, E1, E2 = E
    w = 1.0 / np.asarray(h, float)
    syy = float(np.sum(w * E0[2:]))
    sxy = np.array([np.sum(w * E1[1:]), np.sum(w * E2)])
    c = np.sum(w * E1[:-1])
    sxx = np.array([[np.sum(w * E0[1:-1]), c], [c, np.sum(w * E0[:-2])]])
    return syy, sxy, sxx


def neg_log_lik(a1: float, a2: float, q: float, terms: tuple, h: np.ndarray, N: int, n_axes: int = 3) -> float:
    """−log L of eq. (2) at (a, q) from the weighted terms."""
    syy, sxy, sxx = terms
    f = syy - 2 * (a1 * sxy[0] + a2 * sxy[1]) + a1**2 * sxx[0, 0] + 2 * a1 * a2 * sxx[0, 1] + a2**2 * sxx[1, 1]
    return 0.5 * N * np.log(q) + 0.5 * n_axes * float(np.sum(np.log(h))) + 0.5 * f / q


def fit_hetero(E: list[np.ndarray], u: np.ndarray, N: int, sigma_bounds: tuple, phi_max: float,
               lambdas: np.ndarray = LAMBDA_GRID) -> tuple[float, float, float, float, np.ndarray]:
    """(a_1, a_2, q, λ, h) minimising eq. (2): the weighted AR(2) M-step per λ on the grid, the best λ kept."""
    best = None
    for lam in lambdas:
        h = scale_for(u, lam)
        terms = weighted_terms(E, h)
        a1, a2, q = fit_ar2(*terms, N, sigma_bounds, phi_max)
        val = neg_log_lik(a1, a2, q, terms, h, N)
        if best is None or val < best[0]:
            best = (val, a1, a2, q, float(lam), h)
    return best[1:]


def update_hetero(vel_state: dict, block, nRk: np.ndarray, record: dict | None, sigma_bounds: tuple,
                  tau_bounds: tuple) -> float:
    """One EM step of (a_1, a_2, q, λ) (module docstring); vel_state["intensity"] holds u (K−1,) and
    vel_state["ar2"] becomes (a_1, a_2, HeteroQ). Returns the largest change (|Δa|, |Δ ln q|, |Δ ln(1+λ)|)."""
    from imugraph.calibration.velocity_ar2 import lag_moments
    from imugraph.calibration.velocity_process import chain_inverse_bands

    from imugraph.factors.velocity import ar2_residuals

    probe = ar2_residuals(np.ones((4, 1)), 0.0, 0.0, HeteroQ(1.0, np.full(2, 4.0)))
    if not np.allclose(probe[2:], 0.5):
        raise NotImplementedError("Options.estimate_velocity_process='hetero_ar2': the graph does not whiten the "
                                  "AR(2) innovations by their scale h (install benchmarks/h9_hetero_patch.py first)")
    s = np.asarray(vel_state["s"], float)
    K = len(s)
    if K < 5:
        return 0.0
    Z = chain_inverse_bands(block, nRk, s)
    E = lag_moments(s[:, :3], Z)
    dt = float(np.median(block.dt_k))
    phi_max = float(np.exp(-dt / tau_bounds[1]))
    a1, a2, q, lam, h = fit_hetero(E, vel_state["intensity"], 3 * (K - 2), sigma_bounds, phi_max)
    prev = vel_state.get("ar2")
    if prev is None:
        phi = np.exp(-dt / float(np.max(vel_state["tau"])))
        prev = (phi, 0.0, float(np.min(vel_state["sigma"])) ** 2 * (1 - phi**2))
    lam_prev = getattr(prev[2], "lam", 0.0)
    change = max(abs(a1 - prev[0]), abs(a2 - prev[1]), abs(np.log(q / float(prev[2]))),
                 abs(np.log1p(lam) - np.log1p(lam_prev)))
    gamma0, rho1 = ar2_stationary(a1, a2, q)
    vel_state["ar2"] = (a1, a2, HeteroQ(q, h, lam))
    vel_state["sigma"] = float(np.sqrt(gamma0))
    vel_state["tau"] = float(np.clip(-dt / np.log(np.clip(rho1, 1e-9, 1 - 1e-9)), *tau_bounds))
    if record is not None:
        record["velocity_ar2"] = [a1, a2, q]
        record["velocity_lambda"] = lam
        record["velocity_sigma"], record["velocity_tau"] = vel_state["sigma"], vel_state["tau"]
    return float(change)
