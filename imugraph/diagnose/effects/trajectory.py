"""The gyro's effect on the fitted trajectory with the keyframes fixed (module doc of effects/base.py,
rule 1): the first-order form (E1)–(E3) for Jacobians (`gyro_refit`) and the exact re-integration between
the keyframes for a correction's residuals (`gyro_exact`, `reintegrate`)."""

from __future__ import annotations

import numpy as np

from imugraph.diagnose.effects.base import CHANNELS, replace_session


def interval_index(fit) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe interval k of each sample (N,) and its start sample s_k (N,) (last sample: own interval)."""
    kf = np.asarray(fit.keyframe_samples, int)
    k = np.clip(np.searchsorted(kf, np.arange(fit.n), side="right") - 1, 0, len(kf) - 1)
    return k, kf[k]


def interval_mean(fit, x: np.ndarray) -> np.ndarray:
    """(N, d) per-sample mean of x over the sample's keyframe interval (NaN-aware)."""
    k, _ = interval_index(fit)
    ok = np.all(np.isfinite(x), axis=1)
    K = int(k.max()) + 1
    sums = np.zeros((K, x.shape[1]))
    np.add.at(sums, k[ok], x[ok])
    cnt = np.bincount(k[ok], minlength=K).astype(float)
    means = sums / np.maximum(cnt, 1)[:, None]
    means[cnt == 0] = np.nan
    return means[k]


def gyro_refit(fit, d_omega: np.ndarray) -> tuple[dict, np.ndarray]:
    """Residuals (E1)–(E3) after the gyro changes by Δω (N, 3) rad/s with the keyframes fixed.

    Returns (residuals dict, δθ (N, 3) body-frame orientation change)."""
    d_omega = np.nan_to_num(np.asarray(d_omega, float))
    dt = fit.session.dt
    kf = np.asarray(fit.keyframe_samples, int)
    C = np.concatenate([np.zeros((1, 3)), np.cumsum(d_omega * dt[:, None], axis=0)])   # C_j = Σ_{i<j}
    k, s_k = interval_index(fit)
    s_next = kf[np.minimum(k + 1, len(kf) - 1)]
    has_next = k < len(kf) - 1
    phi = C[np.arange(fit.n)] - C[s_k]                                                  # φ_j (E1)
    Phi = np.where(has_next[:, None], C[s_next] - C[s_k], 0.0)                          # Φ_k
    span = np.maximum(s_next - s_k, 1)
    u = np.where(has_next, (np.arange(fit.n) - s_k) / span, 0.0)
    dtheta = phi - u[:, None] * Phi                                                      # δθ_j (E1)
    T = np.where(has_next, fit.session.t[s_next] - fit.session.t[s_k], 1.0)
    bRn = np.transpose(fit.nRb, (0, 2, 1))
    h_acc = bRn @ np.array([0.0, 0.0, fit.g])
    b_nmag = bRn @ fit.calibration.n_mag
    out = {c: fit.residuals[c].copy() for c in CHANNELS}
    out["gyr"] = out["gyr"] + Phi / T[:, None]                                           # (E2)
    out["acc"] = out["acc"] + np.cross(dtheta, h_acc)                                    # (E3)
    out["mag"] = out["mag"] + np.cross(dtheta, b_nmag) @ np.asarray(fit.calibration.D).T  # (E3)
    return out, dtheta


def reintegrate(fit, gyr: np.ndarray) -> np.ndarray:
    """(N, 3, 3) nRb with the fit's keyframes R̂_k fixed and the samples between them integrated from `gyr`
    at the fit's bias (forward from R̂_k, backward from R̂_{k+1}, slerp-blended: as the fit does)."""
    from imugraph.factors.gyro import keyframe_layout
    from imugraph.geometry import quat_to_rotmat
    from imugraph.graphs.orientation_init import sample_orientations

    kf, skf = keyframe_layout(fit.n, int(fit.info["stride"]), fit.session.dt)
    pre = _rotations_only(np.asarray(gyr, float), fit.session.dt, kf, skf, np.asarray(fit.b_gyr_bias, float))
    return quat_to_rotmat(sample_orientations(fit.nRb[kf], pre))


def reintegrate_matrices(fit, gyr: np.ndarray, nRk: np.ndarray) -> np.ndarray:
    """`reintegrate` with keyframes nRk (K, 3, 3) given, as rotation matrices without the quaternion round
    trip of graphs/orientation_init.sample_orientations (same formula, the joint fit's inner loop):

        nRb_j = R_k Exp(u_j ε_k) ΔR_{k,j},   ε_k = Log(R_kᵀ R_{k+1} ΔR_kᵀ),   u_j: position in the interval"""
    from imugraph.factors.gyro import keyframe_layout
    from imugraph.geometry import expmap, logmap

    kf, skf = keyframe_layout(fit.n, int(fit.info["stride"]), fit.session.dt)
    pre = _rotations_only(np.asarray(gyr, float), fit.session.dt, kf, skf, np.asarray(fit.b_gyr_bias, float))
    k, K = pre.sample_kf, len(nRk)
    if K < 2:
        return nRk[k] @ pre.kRb
    eps = np.zeros((K, 3))
    eps[:-1] = logmap(np.transpose(nRk[:-1], (0, 2, 1)) @ nRk[1:] @ np.transpose(pre.delta_R[:K - 1], (0, 2, 1)))
    k_next = np.minimum(k + 1, K - 1)
    s_k = pre.kf_samples[k]
    u = np.where(k < K - 1, (np.arange(len(k)) - s_k) / np.maximum(pre.kf_samples[k_next] - s_k, 1), 0.0)
    return nRk[k] @ expmap(u[:, None] * eps[k]) @ pre.kRb


def _rotations_only(gyr: np.ndarray, dt: np.ndarray, kf: np.ndarray, skf: np.ndarray, bias: np.ndarray):
    """The rotation part of imugraph.factors.gyro.preintegrate (no covariance, no bias Jacobian, which
    `reintegrate` does not use), same layout and same Exp:

        ΔR_{k,j} = Π_{i=s_k}^{j−1} Exp((y_i − b) Δt_i),   ΔR_k = ΔR_{k,s_{k+1}}      (preintegration)

    bias: (3,) or per-sample (N, 3) rad/s, as preintegrate takes it. Returns a Preintegration with
    kf_samples, sample_kf, kRb and delta_R set (the other fields empty)."""
    from imugraph.factors.gyro import Preintegration, exp_and_right_jacobian

    n, K = gyr.shape[0], len(kf)
    rows = bias[None, :] if bias.ndim == 1 else bias[np.minimum(np.arange(n), len(bias) - 1)]  # (3,) or (N, 3)
    theta = (gyr - rows) * dt[:, None]
    lengths = np.diff(np.append(kf, n))
    L = int(lengths.max())
    pos = np.arange(L)
    valid = pos[:, None] < lengths[None, :]                            # (L, K)
    idx = np.where(valid, pos[:, None] + kf[None, :], n)
    inc, _ = exp_and_right_jacobian(np.concatenate([theta, np.zeros((1, 3))])[idx])   # Exp(0) = I past the end
    R_at = np.empty((K, L, 3, 3))
    R = np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
    for p in range(L):
        R_at[:, p] = R
        R = R @ inc[p]
    if np.all(lengths[:-1] == L):
        kRb = R_at.reshape(-1, 3, 3)[:n]
    else:
        kRb = np.empty((n, 3, 3))
        kRb[idx.T[valid.T]] = R_at[valid.T]
    empty = np.zeros((0,))
    return Preintegration(kf, skf, kRb, R[:-1], empty, empty, empty, empty)


def gyro_exact(fit, d_omega: np.ndarray) -> dict:
    """Residuals (R1)–(R3) after the gyro changes by Δω (N, 3) with the keyframes fixed, evaluated exactly
    (samples re-integrated from y + Δω, `reintegrate`) instead of to first order (E1)–(E3). The gyro
    residual's σ (σ_ω/√M) is so small that the second-order terms of (E2) (|Φ_k|·|rotation in the
    interval|/T_k, e.g. 0.006 rad · 0.3 rad / 0.2 s ≈ 0.01 rad/s for a 2 % scale error) are many σ: the
    linear form serves for Jacobians (gyro_refit), this one for a correction's residuals."""
    from dataclasses import replace as dc_replace

    from imugraph.diagnose.fit import _raw_residuals, body_rate

    d_omega = np.nan_to_num(np.asarray(d_omega, float))
    if not np.any(d_omega):
        return {c: fit.residuals[c].copy() for c in CHANNELS}
    cal = fit.calibration
    key = _digest(d_omega, fit.nRb, fit.session.gyr, fit.session.acc, fit.session.mag, fit.b_gyr_bias, cal.D,
                  cal.o, cal.n_mag, [fit.g, fit.info["stride"]])
    if key not in _EXACT_CACHE:               # the same correction is evaluated by fit, residuals, size
        gyr = fit.session.gyr + d_omega
        nRb = reintegrate(fit, gyr)
        moved = dc_replace(fit, session=replace_session(fit.session, gyr=gyr), nRb=nRb,
                           b_omega=body_rate(nRb, fit.session.dt))
        if len(_EXACT_CACHE) >= 4:
            _EXACT_CACHE.pop(next(iter(_EXACT_CACHE)))
        _EXACT_CACHE[key] = _raw_residuals(moved)
    return {c: v.copy() for c, v in _EXACT_CACHE[key].items()}


_EXACT_CACHE: dict = {}


def _digest(*arrays) -> str:
    """Content hash of arrays (the cache key of gyro_exact: same inputs, same residuals)."""
    import hashlib

    h = hashlib.sha1()
    for a in arrays:
        h.update(np.ascontiguousarray(a, float).tobytes())
    return h.hexdigest()


_COLUMN_CACHE: dict = {}


def cached_columns(fit, tag: str, build):
    """`build()` cached per (tag, fit object): an effect's Jacobian columns (E1)–(E3) depend on the fit
    only, not on the training mask, so the cross-validation's folds share them (same numbers, built once).
    The fit is held in the cache entry so that its id stays unique while the entry lives."""
    key = (tag, id(fit), id(fit.residuals), id(fit.nRb))
    hit = _COLUMN_CACHE.get(key)
    if hit is None or hit[0] is not fit:
        if len(_COLUMN_CACHE) >= 4:
            _COLUMN_CACHE.pop(next(iter(_COLUMN_CACHE)))
        hit = _COLUMN_CACHE[key] = (fit, build())
    return hit[1]
