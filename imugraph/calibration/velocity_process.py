"""Maximum-likelihood parameters of the velocity process (σ_v, τ_v) inside the ML loop (EM step).

The velocity chain (imugraph.factors.velocity) models the sensor's nav-frame velocity as a stationary
first-order Gauss–Markov process with stationary std σ_v and correlation time τ_v, isotropic or one
horizontal and one vertical process (mode "…_hv"; each axis its own chain, written here for n = 3 axes
sharing one process — a group of n axes replaces 3 by n):

    v_0 ~ N(0, σ_v² I),   v_{k+1} = φ_k v_k + w_k,   φ_k = exp(−Δt_k/τ_v),   w_k ~ N(0, σ_v² (1 − φ_k²) I)

Instead of fixing (σ_v, τ_v), each ML round re-estimates them from the round's smoothed velocities, like
Σω, Σa, Σm are re-estimated from the residuals. This is the M-step of expectation-maximisation (Shumway
& Stoffer 1982, for the parameters of a linear state-space model): maximise the expected log-density of
the velocity states under their posterior, whose moments are the smoothed means m_k plus the posterior
covariances P_k,k = Cov(v_k), C_k = Cov(v_k, v_{k+1}) (per axis, equal across isotropic axes):

    E|v_k|²          = |m_k|² + 3 P_k,k
    E[v_k · v_{k+1}] = m_k · m_{k+1} + 3 C_k

    −log L(σ, τ) = (3K/2) ln σ² + (3/2) Σ_k ln(1 − φ_k²)
                   + [E|v_0|² + Σ_k E|v_{k+1} − φ_k v_k|² / (1 − φ_k²)] / (2σ²)         (+ const)

For fixed τ the σ² minimising it is closed form, σ̂²(τ) = [ … ] / (3K), so τ is a bounded 1-D search on
the profile −log L(σ̂(τ), τ) (any keyframe spacing). With uniform Δt and conditioning on v_0 the whole
estimate is the closed form of an AR(1) process (`ar1_closed_form`): the lag-1 autocorrelation gives τ,

    φ̂ = Σ E[v_k · v_{k+1}] / Σ E|v_k|²,   τ̂ = −Δt / ln φ̂,   σ̂² = Σ E|v_{k+1} − φ̂ v_k|² / (3(K−1)(1 − φ̂²)).

The posterior covariances are those of the velocity chain at the round's orientations (tridiagonal
precision per axis: v_0 prior, robust-weighted accelerometer increments, Gauss–Markov terms, rest priors;
Takahashi's recursion gives its diagonal and first off-diagonal of the inverse in O(K)). They ignore the
orientation uncertainty (tilt couples to the velocity drift), so they are a lower bound: without them the
step would use the means alone, which the prior shrinks, and EM would drift toward a tighter prior.

Modes "…_ar2" replace the chain by a second-order (AR(2)) process, estimated the same way
(imugraph.calibration.velocity_ar2).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cholesky_banded
from scipy.optimize import minimize_scalar

from imugraph.factors.velocity import gauss_markov

SIGMA_BOUNDS = (0.01, 5.0)     # m/s
TAU_BOUNDS = (0.05, 30.0)      # s


def chain_covariance(block, nRk: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posterior variances P_k,k (K, 3) and lag-1 covariances C_k (K−1, 3) per nav axis of the velocity
    chain of a `VelocityBlock` at orientations nRk (K, 3, 3) and states s (K, 3 or 6), orientations held:
    the first two bands of the inverse of its precision (`chain_bands`; tridiagonal for the first-order
    chain: Λ_00 += 1/σ_v²; interval k: a_k = w_k/σ_dv,k² on [[1, −1], [−1, 1]], b_k = 1/σ_w,k² on
    [[φ_k², −φ_k], [−φ_k, 1]]; rest keyframe k: Λ_kk += 1/σ_rest²)."""
    Z = chain_inverse_bands(block, nRk, s, 2 if block.ar2 is None else 3)   # tridiagonal for first order
    return Z[0], Z[1, :-1]


def chain_inverse_bands(block, nRk: np.ndarray, s: np.ndarray, bands: int = 3) -> np.ndarray:
    """The first `bands` bands of Λ⁻¹ per nav axis (bands, K, 3) from the chain's first `bands` precision bands."""
    ab = chain_bands(block, nRk, s)[:bands]
    return np.stack([banded_inverse_bands(ab[:, :, i]) for i in range(3)], axis=2)


def banded_inverse_bands(ab: np.ndarray) -> np.ndarray:
    """Bands of Z = Λ⁻¹ for a symmetric positive-definite banded Λ in lower form ab (b+1, K), ab[i, j] =
    Λ_{j+i, j}; returns the same layout for Z.

    Λ = L D Lᵀ (unit lower L with L_{j+i,j} = c_ij/c_0j and d_j = c_0j² from the Cholesky factor c);
    Takahashi's recursion, backwards in j:  Z_{j+m,j} = −Σ_{l=1..b} L_{j+l,j} Z_{j+l,j+m} (m = 1..b),
    Z_jj = 1/d_j − Σ_l L_{j+l,j} Z_{j+l,j}; every Z used lies inside the band.
    """
    c = cholesky_banded(np.asarray(ab, float), lower=True)
    b, K = c.shape[0] - 1, c.shape[1]
    # plain Python floats in the recursion (a few operations per j: numpy scalar indexing costs ~10× more)
    L = (c / c[0]).T.tolist()                  # L[j][l] = L_{j+l, j}
    d_inv = (1.0 / c[0] ** 2).tolist()
    Z = [[0.0] * (b + 1) for _ in range(K)]    # Z[j][m] = Z_{j+m, j}
    for j in range(K - 1, -1, -1):
        ls = range(1, min(b, K - 1 - j) + 1)
        Lj, Zj = L[j], Z[j]
        for m in ls:
            acc = 0.0
            for l in ls:                       # Z_{j+l, j+m}: in the band (|l − m| ≤ b)
                acc += Lj[l] * (Z[j + m][l - m] if l >= m else Z[j + l][m - l])
            Zj[m] = -acc
        Zj[0] = d_inv[j] - sum(Lj[l] * Zj[l] for l in ls)
    return np.array(Z).T


def chain_bands(block, nRk: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Lower-form bands (3, K, 3 axes) of the velocity chain's posterior precision per nav axis at
    orientations nRk and states s (orientations held): v_0 prior, robust-weighted accelerometer increments,
    the Gauss–Markov rows (with an AR(2) block only v_1 | v_0), the AR(2) terms, rest priors."""
    _, _, w, phi, sigma_w, _, _ = block.terms(nRk, s)
    K = block.n_keyframes
    ab = np.zeros((3, K, 3))
    a = (w / block.sigma_dv**2)[:, None]
    bgm = 1.0 / sigma_w**2                               # 0 where σ_w = ∞ (AR(2) block)
    ab[0, 0] += 1.0 / block._prior_sigma()[:3] ** 2
    ab[0, :-1] += a + bgm * phi**2
    ab[0, 1:] += a + bgm
    ab[1, :-1] += -a - bgm * phi
    if block.ar2 is not None:
        a1, a2, q = block.ar2
        c = np.array([-a2, -a1, 1.0]) / np.sqrt(q)       # on (v_{k−1}, v_k, v_{k+1}), k = 1 … K−2
        h = getattr(q, "h", None)                        # per-innovation scale (velocity_hetero.HeteroQ)
        inv_h = (1.0 / np.asarray(h, float) if h is not None else np.ones(K - 2))[:, None]
        for i in range(3):
            ab[0, i:K - 2 + i] += c[i] ** 2 * inv_h
        ab[1, 0:K - 2] += c[0] * c[1] * inv_h
        ab[1, 1:K - 1] += c[1] * c[2] * inv_h
        ab[2, 0:K - 2] += c[0] * c[2] * inv_h
    if block.rest is not None:
        ab[0, np.asarray(block.rest, bool)] += 1.0 / block.sigma_rest**2
    return ab


def moments(m: np.ndarray, P: np.ndarray | None = None, C: np.ndarray | None = None):
    """Posterior second moments per axis: E[v_k,i²] (K, n) and E[v_k,i v_k+1,i] (K−1, n) from means
    m (K, n) and the per-axis covariances P (K, n), C (K−1, n) (None: the means alone)."""
    m = np.asarray(m, float)
    s0 = m**2 + (0.0 if P is None else np.asarray(P, float))
    s1 = m[:-1] * m[1:] + (0.0 if C is None else np.asarray(C, float))
    return s0, s1


def gm_neg_log_lik(tau: float, s0: np.ndarray, s1: np.ndarray, dt_k: np.ndarray,
                   sigma_bounds: tuple = (0.0, np.inf)) -> tuple[float, float]:
    """−log L at σ̂(τ) (module docstring; σ̂ held inside sigma_bounds, the constrained optimum since −log L
    is unimodal in σ²) and that σ̂², for per-axis second moments s0 (K, n), s1 (K−1, n) of n axes sharing
    one process (n = 3 in the module docstring)."""
    s0, s1 = np.asarray(s0, float), np.asarray(s1, float)
    if s0.ndim == 1:
        s0, s1 = s0[:, None], s1[:, None]
    n = s0.shape[1]
    s0, s1 = s0.sum(axis=1), s1.sum(axis=1)
    phi, unit_w = gauss_markov(dt_k, 1.0, tau)          # unit_w² = 1 − φ_k²
    q = unit_w**2
    # E|v_{k+1} − φ v_k|² = E|v_{k+1}|² − 2φ E[v_k·v_{k+1}] + φ² E|v_k|²
    e_step = s0[1:] - 2.0 * phi * s1 + phi**2 * s0[:-1]
    K = len(s0)
    total = s0[0] + np.sum(e_step / q)
    sig2 = float(np.clip(total / (n * K), max(sigma_bounds[0] ** 2, 1e-12), sigma_bounds[1] ** 2))
    return 0.5 * n * K * np.log(sig2) + 0.5 * n * np.sum(np.log(q)) + 0.5 * total / sig2, sig2


def fit_gauss_markov(s0: np.ndarray, s1: np.ndarray, dt_k: np.ndarray,
                     tau_bounds: tuple = TAU_BOUNDS, sigma_bounds: tuple = SIGMA_BOUNDS) -> tuple[float, float]:
    """ML (σ_v, τ_v) of the isotropic Gauss–Markov chain from posterior second moments s0, s1 and the
    interval lengths dt_k: bounded search over ln τ on the profile likelihood, σ̂ closed form."""
    res = minimize_scalar(lambda x: gm_neg_log_lik(np.exp(x), s0, s1, dt_k, sigma_bounds)[0],
                          bounds=(np.log(tau_bounds[0]), np.log(tau_bounds[1])), method="bounded",
                          options={"xatol": 1e-4})
    tau = float(np.exp(res.x))
    return float(np.sqrt(gm_neg_log_lik(tau, s0, s1, dt_k, sigma_bounds)[1])), tau


def ar1_closed_form(s0: np.ndarray, s1: np.ndarray, dt: float) -> tuple[float, float]:
    """(σ_v, τ_v) of an AR(1) chain with uniform spacing dt, conditional on v_0 (module docstring), from
    per-axis moments s0 (K, n), s1 (K−1, n)."""
    n = 1 if np.ndim(s0) == 1 else np.shape(s0)[1]
    phi = float(np.sum(s1) / np.sum(s0[:-1]))
    e_step = np.sum(s0[1:]) - 2.0 * phi * np.sum(s1) + phi**2 * np.sum(s0[:-1])
    sig2 = e_step / (n * (len(s0) - 1) * (1.0 - phi**2))
    return float(np.sqrt(sig2)), float(-dt / np.log(phi))


MODES = ("off", "bounded", "free", "bounded_hv", "free_hv", "bounded_ar2", "free_ar2", "map_ar2", "hetero_ar2",
         "capped_ar2")


def process_bounds(mode: str, sigma_v, tau_v) -> tuple[tuple, tuple]:
    """(σ bounds, τ bounds) of the estimate. "free": the physical ranges SIGMA_BOUNDS, TAU_BOUNDS;
    "bounded": σ_v only above and τ_v only below the configured values (their smallest σ, largest τ when
    per axis), so the short-term steps (the acceleration spectral density 2σ_v²/τ_v) can only loosen and
    the stationary spread σ_v never tightens. A suffix "_hv" (`update_velocity_process`) or "_ar2" is ignored.
    "capped": τ_v only below the configured value, σ_v (and the AR(2) step variance q) free — H9: the free AR(2)
    estimates match the optical innovation variance on the rotation trials (q within 1.1–2×), but on 01/04/06/24/26
    add a slow real root ≈ 0.97–0.99 (σ_v 0.24–0.41 m/s, τ_v 8–15 s against optical 0.04–0.10 m/s): the drift
    the velocity absorbs; the cap removes that drift and keeps the identified steps. Measured (all 17,
    benchmarks/h9_velocity_trace.py --opt estimate_velocity_process="'capped_ar2'"): tilt best of all variants
    (06 inclination 0.345 → 0.279°, 01 0.454 → 0.399°) but mean 0.666° → 0.694°: the gyro map's settling gate
    fails on 01/02/04 (contraction 0.58/0.81/0.77; 01 1.018°, 04 0.866°) and 06/07 heading grows. Not adopted.

    Why "bounded" exists: on rotation-only recordings the velocity states also absorb the integrated
    accelerometer errors (scale, misalignment — not in the model), so the free estimate follows that drift:
    BROAD 04 τ_v → 30 s, σ_v 0.35 m/s against 0.05 m/s optical, 0.55 → 1.11° (benchmarks/v1_velocity_process.py).
    """
    if mode not in MODES[1:]:
        raise ValueError(f"Options.estimate_velocity_process: found {mode!r}, expected one of {MODES}")
    if mode.startswith(("free", "map", "hetero")):   # "map_ar2": a prior instead (velocity_ar2); "hetero_ar2":
        #   the innovation variance follows the motion intensity (velocity_hetero)
        return SIGMA_BOUNDS, TAU_BOUNDS
    s_lo, t_hi = float(np.min(sigma_v)), float(np.max(tau_v))
    tau_b = (TAU_BOUNDS[0], float(np.clip(t_hi, 2 * TAU_BOUNDS[0], TAU_BOUNDS[1])))
    if mode.startswith("capped"):    # only the correlation time bounded: no slow drift, free steps (H9)
        return SIGMA_BOUNDS, tau_b
    return (float(np.clip(s_lo, *SIGMA_BOUNDS)), SIGMA_BOUNDS[1]), tau_b


def update_velocity_process(vel_state: dict, block, nRk: np.ndarray, record: dict | None = None,
                            mode: str = "free", sigma_v=0.5, tau_v=2.0, prior_strength: float = 0.0,
                            em_inner: int = 1) -> float:
    """One EM step of (σ_v, τ_v) from a round's solution; updates vel_state["sigma"], vel_state["tau"]
    and returns the largest |log change| (for the ML loop's convergence test).

    One isotropic process, or with mode "…_hv" one horizontal (x, y) and one vertical (z) process (σ_v, τ_v
    then (3,) arrays): a hand-carried sensor's vertical and horizontal motion differ (BROAD 16, optical:
    0.45, 0.52, 1.15 m/s in x, y, z), and only the horizontal velocity trades against tilt.

    Args:
        vel_state: the ML loop's velocity state (s: (K, 3|6) solved states, sigma, tau);
        block: the round's VelocityBlock (its σ_v, τ_v, increments, robust weights, rest priors);
        nRk: (K, 3, 3) the round's keyframe orientations; record: history entry to note the values in;
        mode, sigma_v, tau_v: MODES entry and the configured process (bounds: `process_bounds`);
        prior_strength: ν_0 of mode "map_ar2" (pseudo-innovations of the settings' process, velocity_ar2);
        em_inner: EM steps of an AR(2) process at the round's orientations (calibration/velocity_em.py; 1: one).
    """
    sigma_bounds, tau_bounds = process_bounds(mode, sigma_v, tau_v)
    if mode.endswith("_ar2"):        # second-order process: calibration/velocity_ar2.py (velocity_hetero.py)
        from imugraph.calibration.velocity_ar2 import update_ar2
        from imugraph.calibration.velocity_em import em_at_orientations
        prior = (float(np.min(sigma_v)), float(np.max(tau_v)), float(prior_strength)) if mode == "map_ar2" else None
        if mode == "hetero_ar2" and vel_state.get("intensity") is not None:
            from imugraph.calibration.velocity_hetero import update_hetero

            def step(st, b):
                return update_hetero(st, b, nRk, record, sigma_bounds, tau_bounds)
        else:
            def step(st, b):
                return update_ar2(st, b, nRk, record, sigma_bounds, tau_bounds, prior)
        return em_at_orientations(vel_state, block, nRk, step, int(em_inner))
    s = np.asarray(vel_state["s"], float)
    P, C = chain_covariance(block, nRk, s)
    s0, s1 = moments(s[:, :3], P, C)
    groups = ([0, 1], [2]) if mode.endswith("_hv") else ([0, 1, 2],)
    sigma, tau = np.empty(3), np.empty(3)
    for axes in groups:
        sigma[axes], tau[axes] = fit_gauss_markov(s0[:, axes], s1[:, axes], block.dt_k, tau_bounds, sigma_bounds)
    if len(groups) == 1:
        sigma, tau = float(sigma[0]), float(tau[0])
    change = float(np.max(np.abs(np.r_[np.log(sigma / np.asarray(vel_state["sigma"], float)),
                                       np.log(tau / np.asarray(vel_state["tau"], float))])))
    vel_state["sigma"], vel_state["tau"] = sigma, tau
    if record is not None:
        record["velocity_sigma"], record["velocity_tau"] = np.asarray(sigma).tolist(), np.asarray(tau).tolist()
    return change
