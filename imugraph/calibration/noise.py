"""Re-estimation of the noise covariances Σω, Σa, Σm from the residuals of the MAP solution
(Kok & Schön 2016, sec. IV: maximum likelihood over the noise levels, alternated with the state solve).

For a channel c with whitened-by-current-σ residuals, the ML variance per axis is corrected for the
degrees of freedom the fit absorbs (E[ê ᵀê] = σ²(n − p_c)): the keyframe rotations' 3 dof are shared
between channels in proportion to the information each channel gives that keyframe (trace of its
Gauss–Newton block), and the global parameters are charged to the channel that sees them.

    σ_c,axis² = Σ_j w_j ê_j,axis² / (Σ_j w_j − p_c / 3)

Real residuals are not white (linear accelerations, slowly varying field disturbances): n correlated
samples carry the information of n/τ independent ones, τ = 1 + 2 Σ_l ρ(l) the integrated autocorrelation
time (Sokal's automatic window: the smallest M ≥ c·τ(M), c = 5). The factor graph, which treats samples
as independent, is therefore given σ_eff = σ·√τ: the quasi-likelihood (effective sample size) correction.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.graphs.measurements import MeasurementBlock


def _channel_info_trace(block: MeasurementBlock, name: str, nRk: np.ndarray, theta: np.ndarray):
    """Raw residuals e (M, 3) of channel `name` and the trace of its Gauss–Newton block per keyframe (K,)."""
    e = block.raw_residuals(name, nRk, theta)
    G11, *_ = block.channel_blocks(name, nRk, theta, with_theta=False)
    return e, np.trace(G11, axis1=1, axis2=2)


def tridiagonal_inverse_diagonal(diag: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Diagonal of A⁻¹ for a symmetric positive definite tridiagonal A (diagonal (n,), off-diagonal (n−1,)).

    Forward pivots d_i = a_i − b_{i−1}²/d_{i−1}, backward pivots e_i = a_i − b_i²/e_{i+1}; then
    (A⁻¹)_ii = 1/(d_i + e_i − a_i) (both eliminations meet at i). O(n), no overflow."""
    a = np.asarray(diag, float)
    b2 = np.asarray(off, float) ** 2
    n = a.size
    d = np.empty(n)
    e = np.empty(n)
    d[0] = a[0]
    for i in range(1, n):
        d[i] = a[i] - b2[i - 1] / d[i - 1]
    e[-1] = a[-1]
    for i in range(n - 2, -1, -1):
        e[i] = a[i] - b2[i] / e[i + 1]
    return 1.0 / (d + e - a)


def field_dof(G_dd: np.ndarray, dt_k: np.ndarray, sigma_d, tau_d: float) -> float:
    """Degrees of freedom of the magnetometer residuals absorbed by the field perturbation d_k
    (imugraph.factors.field), per nav axis the trace of the smoother's hat matrix:

        p_d = Σ_axes tr(H_a (H_a + Q_a)⁻¹),   H_a = diag_k (G_dd,k)_aa,   Q_a the Gauss–Markov chain precision

    (tridiagonal: d_0/σ_d and (d_{k+1} − φ_k d_k)/σ_w,k). Cross-axis and rotation couplings are neglected.
    G_dd: (K, 3, 3) whitened data information of d_k; dt_k (K−1,) keyframe intervals, s."""
    from imugraph.factors.field import field_sigmas, field_steps

    K = G_dd.shape[0]
    phi, sigma_w = field_steps(dt_k, sigma_d, tau_d)
    sig = field_sigmas(sigma_d)
    total = 0.0
    for a in range(3):
        h = np.clip(G_dd[:, a, a], 0.0, None)
        s2 = sigma_w[:, a] ** 2
        q = np.zeros(K)
        q[0] += 1.0 / sig[a] ** 2
        q[:-1] += phi**2 / s2
        q[1:] += 1.0 / s2
        total += float(np.sum(h * tridiagonal_inverse_diagonal(h + q, -phi / s2)))
    return total


def reestimate(block: MeasurementBlock, nRk: np.ndarray, theta: np.ndarray, gyro_factors: list,
               values: gtsam.Values, sigma_gyr: np.ndarray, extra_dof: dict | None = None) -> dict:
    """New per-axis standard deviations {"gyr", "acc", "mag"} (unchanged channels keep their value).

    Args:
        block: the measurement block at the current noise levels; nRk (K,3,3) and theta (13,) the solution;
        gyro_factors: the AHRSFactors of the graph, or their covariances (K−1, 3, 3) (Preintegration.cov);
        values: the solution; sigma_gyr (3,) current gyro σ;
        extra_dof: channel → further degrees of freedom the fit absorbs (e.g. field_dof for "mag").
    """
    K = block.n_keyframes
    traces, raw = {}, {}
    if block.acc is not None and block.use_acc:
        raw["acc"], traces["acc"] = _channel_info_trace(block, "acc", nRk, theta)
    if block.mag is not None:
        raw["mag"], traces["mag"] = _channel_info_trace(block, "mag", nRk, theta)
    # gyro: each AHRS factor informs both its keyframes
    if isinstance(gyro_factors, np.ndarray):
        cov = gyro_factors
    else:
        cov = np.array([f.preintegratedMeasurements().preintMeasCov() for f in gyro_factors]).reshape(-1, 3, 3)
    g_tr = np.zeros(K)
    if len(cov):
        tr = np.trace(np.linalg.inv(cov), axis1=1, axis2=2)
        g_tr[:len(tr)] += tr
        g_tr[1:len(tr) + 1] += tr
    total = g_tr + sum(traces.values())
    total = np.where(total > 0, total, 1.0)
    out = {}
    for name, e in raw.items():
        ch = getattr(block, name)
        share = traces[name] / total
        p = 3.0 * share.sum() + (13.0 if name == "mag" and block.use_theta else 0.0) + (extra_dof or {}).get(name, 0.0)
        r = e / ch.sigma
        w = ch.kernel.weight(np.linalg.norm(r, axis=1))
        n_eff = max(w.sum() - p / 3.0, 1.0)
        out[name] = np.sqrt(np.sum(w[:, None] * e**2, axis=0) / n_eff)
        out[name + "_tau"] = integrated_autocorrelation(e * np.sqrt(w)[:, None])
    # Σω is not re-estimated here: a chain of between-factors can absorb its own residuals (K states,
    # K−1 factors), so the gyro noise is not identifiable from them; it is measured at rest instead.
    return out


def integrated_autocorrelation(x: np.ndarray, c: float = 5.0, max_lag: int | None = None) -> float:
    """Integrated autocorrelation time τ (in samples) of the rows of x (M, d), averaged over columns.

    ρ(l) from the FFT of the mean-removed series; τ(M) = 1 + 2 Σ_{l=1..M} ρ(l) with Sokal's window.
    """
    x = np.asarray(x, float)
    x = x - x.mean(axis=0)
    m = x.shape[0]
    if m < 8:
        return 1.0
    nfft = 1 << int(np.ceil(np.log2(2 * m)))
    f = np.fft.rfft(x, nfft, axis=0)
    acov = np.fft.irfft(np.sum(np.abs(f) ** 2, axis=1), nfft)[:m]
    if acov[0] <= 0:
        return 1.0
    rho = acov / acov[0]
    lim = max_lag or m // 4
    taus = 1.0 + 2.0 * np.cumsum(rho[1:lim])
    window = np.arange(1, len(taus) + 1)
    ok = np.flatnonzero(window >= c * taus)
    tau = taus[ok[0]] if len(ok) else taus[-1]
    return float(max(tau, 1.0))
