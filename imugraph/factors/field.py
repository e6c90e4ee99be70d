"""A slowly varying perturbation of the nav-frame magnetic field (spatial inhomogeneity, slow drift).

The magnetometer model with a constant Earth field (Kok & Schön 2016, eq. 6) treats every deviation of
the measured field from D·bRn·n_mag + o as white noise. Indoors the field direction changes with position
(steel in floors and furniture): on BROAD trial 01 the field seen through the optical orientation and the
best calibration fitted to it varies by 0.8–0.9° RMS over 10-s averages, and a linear function of the
sensor position explains most of it (0.8° → 0.25°). With white noise at 286 Hz such an error is
trusted ~√(286·10) times more than it deserves, and it pulls tilt and heading with it.

The perturbation is a per-keyframe nav-frame vector d_k (unit-field units) added to the field,

    y_j = D ΔR_jᵀ R_kᵀ (n_mag(δ) + d_k) + o + e_j,     ∂e_j/∂d_k = D ΔR_jᵀ R_kᵀ          (magnetometer.py)

with a first-order Gauss–Markov prior (stationary std σ_d, correlation time τ_d):

    d_0 ~ N(0, σ_d² I),   d_{k+1} = φ_k d_k + w_k,   φ_k = exp(−Δt_k/τ_d),   w_k ~ N(0, σ_d² (1 − φ_k²) I)

The zero mean keeps the long-run average of the field on n_mag(δ) (heading and dip stay defined); within
τ_d the magnetometer still gives relative heading, and the gyro bridges deviations up to ~σ_d.

σ_d may differ per nav axis. A perturbation along y (horizontal, across the field) moves the field as a
heading change does (by cos δ per radian) and as a tilt about the field's horizontal axis does (sin δ);
one in the x–z plane as a tilt about y (the dip direction). A loose σ_y lets the heading follow the gyro,
whose scale/misalignment error (0.2–0.7 % on BROAD, calibration/gyro_map.py) then drifts over many turns
(BROAD 01: 1.60° → 3.60° with σ = 0.015 on every axis), so σ_y is kept small: (0.015, 0.003, 0.015), τ_d =
1 s gives 01 1.60 → 1.22°, 04 1.74 → 1.17°, 10 0.75 → 0.32°, 17-trial mean 0.99 → 0.83° (ml.Options).
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors.velocity import gauss_markov


def field_key(k: int) -> int:
    """Key of keyframe k's field perturbation d_k (Vector3)."""
    return gtsam.symbol("f", int(k))


def field_sigmas(sigma_d) -> np.ndarray:
    """σ_d as (3,) per nav axis (x along the horizontal field, y horizontal across it, z up) from a scalar or
    3 values."""
    return np.broadcast_to(np.asarray(sigma_d, float), (3,)).copy()


def field_steps(dt_k: np.ndarray, sigma_d, tau_d: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss–Markov transitions of the prior: φ_k = exp(−Δt_k/τ_d) (K−1,) and the increments' std
    σ_w,k = σ_d √(1 − φ_k²) (K−1, 3), for keyframe intervals dt_k (K−1,) s."""
    phi, unit_w = gauss_markov(np.asarray(dt_k, float), 1.0, tau_d)
    return phi, unit_w[:, None] * field_sigmas(sigma_d)[None, :]


def field_prior_terms(d: np.ndarray, dt_k: np.ndarray, sigma_d, tau_d: float):
    """Whitened Gauss–Markov residuals of d (K, 3): the start term d_0/σ_d (3,), the increments
    (d_{k+1} − φ_k d_k)/σ_w,k (K−1, 3), and φ (K−1,), σ_w (K−1, 3).

    sigma_d: a scalar, or (3,) per nav axis (`field_sigmas`)."""
    phi, sigma_w = field_steps(dt_k, sigma_d, tau_d)
    start = d[0] / field_sigmas(sigma_d)
    steps = (d[1:] - phi[:, None] * d[:-1]) / sigma_w
    return start, steps, phi, sigma_w
