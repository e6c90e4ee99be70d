"""Gyro errors driven by the motion (g-sensitivity G, scale S, rate-squared scale K), regressed against a
reference orientation over windows — the evidence step of issue 2c/2b (benchmarks/h8_gsens.py).

Model of the rate error (first order, per recording):

    ω_meas = ω + δω,   δω_j = b(t_j) + G·f_j + S·ω_meas,j [+ K·(ω_meas,j ⊙ |ω_meas,j|)] [+ G₂·(f_j ⊙ f_j)]     (1)

b: bias, piecewise constant over bias_seg_s segments; f = b_acc/g0: the specific force in g (gravity included —
the standard MEMS g-sensitivity, typ. 0.01–0.1 °/s/g); S: scale/misalignment (= −E of calibration/gyro_map.py;
the reference's misalignment to the gyro axes enters its antisymmetric part); K: a per-component quadratic
scale; G₂: the g²-sensitivity (vibration rectification, rad/s per g² of each specific-force component). terms="split" replaces G·f by G_grav·g_b + G_lin·(f − g_b) with g_b = nRbᵀ·up from the reference: a
physical g-sensitivity has G_lin = G_grav (a sensor cannot tell gravity from acceleration).

Regression without differentiating the reference (an optical rate is noisy): over non-overlapping windows
[a, e) the gyro's relative rotation ΔR_g = R_aᵀR_e (strapdown R_{k+1} = R_k Exp(ω_k Δt)) and the reference's
ΔR_o = Q_aᵀQ_e (at lag λ samples, slerp) differ, to first order in δω, by

    r_w = Log(ΔR_gᵀ ΔR_o) = −R_eᵀ Σ_{j=a}^{e−1} R_{j+1} δω_j Δt_j                                          (2)

(ΔR_o = Π Exp((ω_j − δω_j)Δt); moving Exp(−δω_j Δt) past the later factors B_j = R_{j+1}ᵀR_e rotates it by
B_jᵀ): linear in the parameters of (1), valid for any rotation inside the window. Ordinary least squares; λ on
a grid by the smallest residual; OLS standard errors from the residual variance (non-overlapping windows).

What a fitted term does to the orientation (predicted_rotation): a linear-acceleration g-sensitivity adds
R_eᵀ Σ R_{j+1} G f_lin,j Δt to (2). Back-and-forth motion alone keeps ∫f_lin dt bounded (a velocity change), but a
body-frame mean of f_lin (centripetal acceleration of a swung sensor: BROAD 16 −0.49 g along x over `movement`)
that G maps onto an axis the body does not turn about grows linearly: 0.07 °/s/g × 0.49 g ≈ 0.35° per 10 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import integrate_gyro, quat_slerp, quat_to_rotmat

G0 = 9.81                               # m/s² per g: G in rad/s per g
DEFAULT_LAGS = np.arange(-3.0, 3.01, 0.25)
_MARGIN = 4                             # samples kept clear of the ends for the lag grid
TERMS = ("base", "split", "rate2", "g2")


def strapdown(gyr: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(N+1, 3, 3) R_k = Π_{i<k} Exp(ω_i Δt_i), R_0 = I (body → integration frame)."""
    q = integrate_gyro(np.vstack([gyr, gyr[-1:]]), np.r_[dt, dt[-1:]])   # the padded last row only sizes q to N+1
    return quat_to_rotmat(q)


def _kron_rows(v: np.ndarray) -> np.ndarray:
    """(N, 3, 9) I₃ ⊗ v_jᵀ: δω_j = M v_j = (I₃ ⊗ v_jᵀ) vec M (row-major)."""
    X = np.zeros((len(v), 3, 9))
    for i in range(3):
        X[:, i, 3 * i:3 * i + 3] = v
    return X


def regressors(t: np.ndarray, gyr: np.ndarray, acc: np.ndarray, terms: str = "base", bias_seg_s: float = 30.0,
               g_b: np.ndarray | None = None) -> tuple[np.ndarray, list[str]]:
    """(N, 3, p) X_j of δω_j = X_j θ in (1), and the parameter names ("b<seg>_x", "S_xy", "G_xz", ...; a 3×3
    block's name is <tag>_<row axis><column axis>, row: gyro axis, column: regressor axis).

    g_b: (N, 3) gravity's specific force in the body frame, in g (terms="split" only)."""
    if terms not in TERMS:
        raise ValueError(f"terms: found {terms!r}, expected one of {TERMS}")
    n = len(t)
    span = t[-1] - t[0]
    seg = np.minimum((t - t[0]) // bias_seg_s, max(span // bias_seg_s - 1, 0)).astype(int)
    nseg = int(seg.max()) + 1
    B = np.zeros((n, 3, 3 * nseg))
    for i in range(3):
        B[np.arange(n), i, 3 * seg + i] = 1.0
    blocks = [B]
    names = [f"b{k}_{'xyz'[i]}" for k in range(nseg) for i in range(3)]

    def add(v: np.ndarray, tag: str) -> None:
        blocks.append(_kron_rows(v))
        names.extend(f"{tag}_{'xyz'[i]}{'xyz'[c]}" for i in range(3) for c in range(3))

    add(gyr, "S")
    f = acc / G0
    if terms == "split":
        if g_b is None:
            raise ValueError("terms='split' needs g_b (gravity's specific force in the body frame, in g)")
        add(g_b, "Ggrav")
        add(f - g_b, "Glin")
    else:
        add(f, "G")
    if terms == "rate2":
        add(gyr * np.abs(gyr), "K")
    if terms == "g2":
        add(f * f, "G2")
    return np.concatenate(blocks, axis=2), names


def window_design(R: np.ndarray, X: np.ndarray, dt: np.ndarray, a: np.ndarray, e: np.ndarray) -> np.ndarray:
    """(W, 3, p) the linear map of eq. (2): r_w = Φ_w θ, Φ_w = −R_eᵀ Σ_{j∈[a,e)} R_{j+1} X_j Δt_j."""
    M = np.einsum("nij,njp->nip", R[1:], X) * dt[:, None, None]
    cs = np.concatenate([np.zeros((1,) + M.shape[1:]), np.cumsum(M, axis=0)])
    return -np.einsum("wji,wjp->wip", R[e], cs[e] - cs[a])


def reference_at(quat: np.ndarray, idx: np.ndarray, lag: float) -> np.ndarray:
    """(W, 3, 3) the reference orientation at sample idx + lag (slerp between neighbours)."""
    pos = np.asarray(idx, float) + lag
    k = np.floor(pos).astype(int)
    return quat_to_rotmat(quat_slerp(quat[k], quat[k + 1], pos - k))


def window_residual(R: np.ndarray, quat_ref: np.ndarray, a: np.ndarray, e: np.ndarray, lag: float) -> np.ndarray:
    """(W, 3) r_w = Log(ΔR_gᵀ ΔR_o) of eq. (2), rad."""
    from scipy.spatial.transform import Rotation

    dRg = np.einsum("wji,wjk->wik", R[a], R[e])
    Qa, Qe = reference_at(quat_ref, a, lag), reference_at(quat_ref, e, lag)
    dRo = np.einsum("wji,wjk->wik", Qa, Qe)
    return Rotation.from_matrix(np.einsum("wji,wjk->wik", dRg, dRo)).as_rotvec()


def usable_windows(mask: np.ndarray, good: np.ndarray, h: int) -> tuple[np.ndarray, np.ndarray]:
    """(a, e) of the non-overlapping h-sample windows inside mask whose reference ends (± the lag margin) are valid."""
    m, n = _MARGIN, len(mask)
    starts = np.arange(m, n - h - m, h)
    ok = [mask[s:s + h + 1].all() and good[s - m:s + m + 1].all() and good[s + h - m:s + h + m + 1].all()
          for s in starts]
    a = starts[np.asarray(ok, bool)] if len(starts) else starts
    return a, a + h


@dataclass
class GyroErrorFit:
    """θ (p,), its covariance (p, p) and names; the lag (samples), residual std per window (rad), windows, dof."""

    theta: np.ndarray
    cov: np.ndarray
    names: list
    lag: float
    sigma: float
    windows: int
    dof: int

    def block(self, tag: str) -> tuple[np.ndarray, np.ndarray]:
        """(3, 3) estimate and standard error of the parameter block `tag` (e.g. "G", "S"), SI units."""
        i = self.index(tag)
        return self.theta[i].reshape(3, 3), np.sqrt(np.diag(self.cov)[i]).reshape(3, 3)

    def index(self, tag: str) -> list[int]:
        return [k for k, nm in enumerate(self.names) if nm.startswith(tag + "_")]

    def wald(self, tag: str) -> tuple[float, float]:
        """F statistic and p-value of "block `tag` = 0" (Wald form, F(q, dof))."""
        from scipy.stats import f as fdist

        i = self.index(tag)
        th, C = self.theta[i], self.cov[np.ix_(i, i)]
        F = float(th @ np.linalg.solve(C, th) / len(i))
        return F, float(fdist.sf(F, len(i), self.dof))


def fit_gyro_errors(session, quat_ref: np.ndarray, mask: np.ndarray | None = None, win_s: float = 1.0,
                    terms: str = "base", bias_seg_s: float = 30.0, lags=DEFAULT_LAGS) -> GyroErrorFit:
    """Least-squares fit of (1) through (2) against quat_ref (N, 4) (w,x,y,z body → nav; NaN rows: none).

    mask: (N,) samples to use (default session.movement); lag chosen on `lags` (samples) by the residual.
    Raises SessionError when fewer windows than unknowns remain.
    """
    quat_ref = np.asarray(quat_ref, float)
    if quat_ref.shape != (session.n, 4):
        raise SessionError(session.source, "quat_ref", f"shape {quat_ref.shape}", f"({session.n}, 4)")
    mask = np.asarray(session.movement if mask is None else mask, bool)
    good = np.all(np.isfinite(quat_ref), axis=1)
    q = np.where(good[:, None], quat_ref, np.array([1.0, 0, 0, 0]))
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    g_b = np.einsum("nji,j->ni", quat_to_rotmat(q), np.array([0, 0, 1.0])) if terms == "split" else None
    X, names = regressors(session.t, session.gyr, session.acc, terms, bias_seg_s, g_b)
    h = int(round(win_s * session.rate))
    a, e = usable_windows(mask, good, h)
    if 3 * len(a) <= X.shape[2]:
        raise SessionError(session.source, "movement", f"{len(a)} usable {win_s:g} s windows",
                           f"more than {X.shape[2] / 3:.0f} windows with a valid reference")
    R = strapdown(session.gyr, session.dt)
    Phi = window_design(R, X, session.dt, a, e)
    keep = np.abs(Phi).sum(axis=(0, 1)) > 0                      # bias segments without a window
    Phi, names = Phi[:, :, keep], [nm for nm, k in zip(names, keep) if k]
    A = Phi.reshape(-1, Phi.shape[2])
    dof = A.shape[0] - A.shape[1]
    if dof < 1:
        raise SessionError(session.source, "movement", f"{len(a)} usable {win_s:g} s windows",
                           f"more than {A.shape[1] / 3:.0f} windows with a valid reference")
    best = None
    for lag in lags:
        y = window_residual(R, q, a, e, float(lag)).ravel()
        theta, *_ = np.linalg.lstsq(A, y, rcond=None)
        rss = float(np.sum((y - A @ theta) ** 2))
        if best is None or rss < best[0]:
            best = (rss, theta, float(lag))
    rss, theta, lag = best
    s2 = rss / dof
    return GyroErrorFit(theta=theta, cov=s2 * np.linalg.pinv(A.T @ A), names=names, lag=lag,
                        sigma=float(np.sqrt(s2)), windows=len(a), dof=dof)


def pooled(estimates: np.ndarray, errors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse-variance pooled value, its standard error, and Cochran's Q/(n−1) per element.

    estimates, errors: (n, ...) per-recording values and standard errors. Q = Σ w_i (x_i − x̄)², w_i = 1/σ_i²;
    Q/(n−1) ≈ 1 when the recordings agree within their errors (a physical constant of one sensor)."""
    x, s = np.asarray(estimates, float), np.asarray(errors, float)
    w = 1.0 / s**2
    mean = (w * x).sum(0) / w.sum(0)
    Q = (w * (x - mean) ** 2).sum(0) / max(len(x) - 1, 1)
    return mean, 1.0 / np.sqrt(w.sum(0)), Q


def predicted_rotation(session, v: np.ndarray, M: np.ndarray, win_s: float, mask: np.ndarray | None = None
                       ) -> float:
    """RMS (rad) over non-overlapping win_s windows inside mask of the rotation error the rate error δω_j = M·v_j
    alone accumulates within a window, by (2): |R_eᵀ Σ R_{j+1} M v_j Δt|."""
    mask = np.asarray(session.movement if mask is None else mask, bool)
    R = strapdown(session.gyr, session.dt)
    h = int(round(win_s * session.rate))
    a, e = usable_windows(mask, np.ones(session.n, bool), h)
    if len(a) == 0:
        return float("nan")
    X = (np.asarray(v, float) @ np.asarray(M, float).T)[:, :, None]
    r = window_design(R, X, session.dt, a, e)[:, :, 0]
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
