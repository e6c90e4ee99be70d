"""Online magnetometer calibration of a stream: running sums, closed-form refit of D, o and the dip.

Model (Kok & Schön): y_i = D·bRn_i·n_mag(δ) + o + e_i, with n_mag(δ) = (cos δ, 0, −sin δ). For given
orientations nRb_i write bRn_i·n_mag = cos δ·u_i + sin δ·w_i with u_i = bRn_i·e_x and w_i = −bRn_i·e_z .
For a fixed δ the model is linear in the calibration, and each magnetometer axis j is a separate regression
with the same design x_i = (b_i, 1):

    y_ij = θ_j·x_i + e_ij,   θ_j = (D_j,: , o_j)                               (1)

so the normal matrix A(δ) = Σ x_i x_iᵀ (4×4) and right-hand side r(δ) = Σ x_i y_iᵀ (4×3) are quadratic in
(cos δ, sin δ) of a fixed set of running sums (Σuuᵀ, Σuwᵀ, Σwwᵀ, Σu, Σw, Σuyᵀ, Σwyᵀ, Σy, Σyyᵀ, N):
constant memory, whatever the length of the stream. A Gaussian prior about the start calibration θ⁰ with
information Λ (per axis) keeps the refit defined while the data hold too little rotation:

    (A/σ_j² + Λ) θ_j = r_j/σ_j² + Λ θ⁰_j                                       (2)

δ: the profile least-squares cost SSE(δ) = Σ_j (Σ y_j² − 2 θ_jᵀ r_j + θ_jᵀ A θ_j) is minimised by a bounded
1-D search. Marginal standard deviations: of θ_j from the inverse of (2)'s matrix (scaled by the reduced χ²
when the residuals are larger than the nominal noise, and by the magnetometer's noise correlation time), of δ
from the curvature of the profile cost, var δ = 2 s² / SSE''(δ).

Residual whiteness: (2)'s covariance treats the residuals as white. Indoors they are not (the field varies
with position; the orientations carry errors of their own — errors in variables — that persist for seconds),
so the reported std is scaled by the batch-means factor of the residuals over the blocks b between refits
(calib_every_s, 2 s):

    F_j = Σ_b (Σ_{i∈b} r_ij)² / Σ_i r_ij²,   r_ij = y_ij − θ_jᵀ x_i                                 (3)

(1 for white residuals, up to the block length in samples for fully correlated ones), computed at the refit's θ
from running sums of the blocks' (Σu, Σw, n, Σy) — constant memory. A constant orientation error stays
invisible (D absorbs it as a misalignment). The swap decision keeps the white-noise std (`std_white`).

Which orientations: the stream folds a keyframe interval in once its keyframe is final enough (it left the
fixed-lag window, or it is `delay_s` old under iSAM2), with its samples' orientations nRk·kRb_i.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import minimize_scalar

from imugraph.calibration.result import Calibration
from imugraph.factors.theta import unpack_theta

__all__ = ["OnlineMagCalibration"]


class OnlineMagCalibration:
    """Running sums of (1) and the refit (2).

    Args:
        cal0: start calibration (prior mean; its noise["mag"] is the nominal σ per axis).
        prior_rel: prior σ of every entry of D and o, relative to the field scale |det D|^(1/3).
        gate: samples whose residual under the current calibration exceeds gate × scale are not used
            (short disturbances).
        estimate_dip: False: δ held at the start calibration's (std then that of the start, or 0).
        use_start_std: the prior's std is the start calibration's own (cal0.std), where it has one.
    """

    def __init__(self, cal0: Calibration, prior_rel: float = 0.2, gate: float = 0.3, estimate_dip: bool = True,
                 use_start_std: bool = False):
        self.cal0, self.estimate_dip = cal0, estimate_dip
        self.scale = float(np.cbrt(abs(np.linalg.det(cal0.D))))
        sig = np.asarray(cal0.noise.get("mag", np.full(3, 0.01 * self.scale)), float).reshape(3)
        self.sig = np.maximum(sig, 1e-6 * self.scale)
        tau = cal0.coverage.get("noise_correlation", {}) if isinstance(cal0.coverage, dict) else {}
        self.corr = max(1.0, float(tau.get("mag", 1.0)))
        # Λ (diagonal, per axis j: row j of `prior_info`): the start calibration's own std when it has one
        # (a bootstrap's), else prior_rel × scale
        self.prior_info = np.full((3, 4), 1.0 / (prior_rel * self.scale) ** 2)
        if use_start_std and cal0.std and "D" in cal0.std and "o" in cal0.std:
            std0 = np.hstack([np.asarray(cal0.std["D"], float).reshape(3, 3), np.asarray(cal0.std["o"], float).reshape(3, 1)])
            ok = np.isfinite(std0) & (std0 > 0)
            self.prior_info[ok] = 1.0 / std0[ok] ** 2
        self.theta0 = np.hstack([cal0.D, cal0.o[:, None]]).T                   # (4, 3): column j = θ⁰_j
        self.gate = gate * self.scale
        self.current = cal0
        self.rejected = 0
        # every running sum of (1) in one matrix: S = Σ ξ_i ξ_iᵀ, ξ_i = (u_i, w_i, 1, y_i) (10,): one product per
        # interval instead of nine (see the properties below)
        self.S = np.zeros((10, 10))
        # residual whiteness (3): the open block's raw sums (Σu, Σw, n, Σy) and, over closed blocks, Σ z zᵀ,
        # Σ z s_yᵀ, Σ s_y² with z = (Σu, Σw, n) of a block
        self._blk = np.zeros(10)
        self.Qb, self.Pb, self.Yb, self.blocks = np.zeros((7, 7)), np.zeros((7, 3)), np.zeros(3), 0.0
        self.std_white = None            # the last refit's std without the whiteness factor (see refit)
        self.last_whiteness = None       # its factor per axis (eq. 3; None before 5 blocks)
        self.history: list = []

    def set_prior(self, centre: np.ndarray, sigma: np.ndarray) -> None:
        """Replace the prior of (2): centre and σ as θ vectors (13,: vec D row-major, o, δ — factors.theta; δ unused)."""
        D, o, _ = unpack_theta(centre)
        D_sig, o_sig, _ = unpack_theta(sigma)
        self.theta0 = np.hstack([D, o[:, None]]).T                                 # (4, 3): column j = θ⁰_j
        self.prior_info = 1.0 / np.hstack([D_sig, o_sig[:, None]]) ** 2

    # ------------------------------------------------------------------ data
    def forget(self, factor: float) -> None:
        """Down-weight everything folded so far by `factor` (0..1): exponential forgetting of samples whose
        orientations were estimated with an older calibration."""
        for name in ("S", "Qb", "Pb", "Yb"):       # in place (the same products; no new arrays)
            getattr(self, name).__imul__(factor)
        self.blocks *= factor

    # the running sums of (1), views into S
    n = property(lambda self: self.S[6, 6], doc="(weighted) number of samples folded in")
    Suu = property(lambda self: self.S[:3, :3])
    Suw = property(lambda self: self.S[:3, 3:6])
    Sww = property(lambda self: self.S[3:6, 3:6])
    Su = property(lambda self: self.S[:3, 6])
    Sw = property(lambda self: self.S[3:6, 6])
    Sy = property(lambda self: self.S[6, 7:])
    Suy = property(lambda self: self.S[:3, 7:])
    Swy = property(lambda self: self.S[3:6, 7:])
    Syy = property(lambda self: self.S[7:, 7:])

    def add(self, y: np.ndarray, nRb: np.ndarray) -> int:
        """Fold in raw field samples y (n, 3) (NaN rows: none) with their orientations nRb (n, 3, 3);
        returns the number used. (The stream's field perturbation d_k is not used: it is zero-mean, and
        folding the graph's d_k in kept the start calibration's error, see stream_online.)"""
        y = np.asarray(y, float).reshape(-1, 3)
        ok = np.isfinite(y).all(axis=1)
        R = np.asarray(nRb, float).reshape(-1, 3, 3)
        if not ok.all():                               # (the fancy indexing only where a row is missing)
            if not ok.any():
                return 0
            y, R = y[ok], R[ok]
        c = self.current
        xi = np.empty((len(y), 10))                    # ξ_i = (u_i, w_i, 1, y_i)
        xi[:, :3], xi[:, 3:6], xi[:, 6], xi[:, 7:] = R[:, 0, :], R[:, 2, :], 1.0, y
        np.negative(xi[:, 3:6], out=xi[:, 3:6])        # u, w = bRn·e_x, −bRn·e_z (rows of nRb)
        pred = (np.cos(c.dip_rad) * xi[:, :3] + np.sin(c.dip_rad) * xi[:, 3:6]) @ c.D.T + c.o
        keep = np.linalg.norm(y - pred, axis=1) <= self.gate
        if not keep.all():
            self.rejected += int((~keep).sum())
            xi = xi[keep]
        self.S += xi.T @ xi
        self._blk += xi.sum(0)
        return len(xi)

    def end_block(self) -> None:
        """Close the current block of samples (the stream closes one at every refit) for the whiteness factor."""
        z, s_y = self._blk[:7], self._blk[7:]
        if z[6] > 0:
            self.Qb += np.outer(z, z)
            self.Pb += np.outer(z, s_y)
            self.Yb += s_y**2
            self.blocks += 1.0
        self._blk = np.zeros(10)

    def whiteness(self, theta: np.ndarray, dip: float) -> np.ndarray | None:
        """Per axis j, F_j = Σ_b (Σ_{i∈b} r_ij)² / Σ_i r_ij² (eq. 3) at θ (4×3), δ; None with < 5 blocks."""
        if self.blocks < 5:
            return None
        c, s = np.cos(dip), np.sin(dip)
        M = np.zeros((4, 7))
        M[:3, :3], M[:3, 3:6], M[3, 6] = c * np.eye(3), s * np.eye(3), 1.0       # x_b = M z_b
        A, r = self._normal(dip)
        Qx, Px = M @ self.Qb @ M.T, M @ self.Pb
        out = np.empty(3)
        for j in range(3):
            th = theta[:, j]
            blk = self.Yb[j] - 2 * th @ Px[:, j] + th @ Qx @ th
            sse = self.Syy[j, j] - 2 * th @ r[:, j] + th @ A @ th
            out[j] = blk / sse if sse > 0 else 1.0
        return out

    # ------------------------------------------------------------------ refit
    def _normal(self, dip: float) -> tuple[np.ndarray, np.ndarray]:
        """A(δ) (4×4) and r(δ) (4×3) of (1) from the running sums."""
        c, s = np.cos(dip), np.sin(dip)
        Sbb = c * c * self.Suu + c * s * (self.Suw + self.Suw.T) + s * s * self.Sww
        Sb = c * self.Su + s * self.Sw
        A = np.empty((4, 4))
        A[:3, :3], A[:3, 3], A[3, :3], A[3, 3] = Sbb, Sb, Sb, self.n
        r = np.vstack([c * self.Suy + s * self.Swy, self.Sy[None]])
        return A, r

    def _solve(self, dip: float) -> tuple[np.ndarray, float, list]:
        """θ (4×3) of (2) at δ, the data SSE, and the per-axis inverse matrices of (2)."""
        A, r = self._normal(dip)
        theta, sse, inv = np.empty((4, 3)), 0.0, []
        for j in range(3):
            M = A / self.sig[j] ** 2 + np.diag(self.prior_info[j])
            M_inv = np.linalg.inv(M)
            theta[:, j] = M_inv @ (r[:, j] / self.sig[j] ** 2 + self.prior_info[j] * self.theta0[:, j])
            sse += (self.Syy[j, j] - 2 * theta[:, j] @ r[:, j] + theta[:, j] @ A @ theta[:, j]) / self.sig[j] ** 2
            inv.append(M_inv)
        return theta, float(sse), inv

    def refit(self, t: float) -> Calibration:
        """Closed-form refit from everything folded in so far; becomes `current` and a `history` row."""
        if self.n < 8:
            self.history.append(self._row(t, self.current, None))
            return self.current
        dip = self.current.dip_rad
        if self.estimate_dip:
            res = minimize_scalar(lambda d: self._solve(d)[1], bounds=(dip - 0.5, dip + 0.5), method="bounded",
                                  options={"xatol": 1e-5})
            dip = float(np.clip(res.x, -np.pi / 2, np.pi / 2))
        theta, sse, inv = self._solve(dip)
        chi2 = max(1.0, sse / max(3 * self.n - 13, 1))        # reduced χ² (≥ 1: never shrink the std)
        var_scale = chi2 * self.corr
        var_th = np.array([np.diag(m) for m in inv])                            # (3, 4): row j = axis j
        self.std_white = {"D": np.sqrt(var_th[:, :3] * var_scale), "o": np.sqrt(var_th[:, 3] * var_scale)}
        self.end_block()
        F = self.whiteness(theta, dip)
        self.last_whiteness = None if F is None else np.maximum(F, self.corr)
        # residuals correlated over seconds (field inhomogeneity, orientation errors: errors in variables):
        # the variance of θ grows by F_j over the white-noise formula; never below the calibration's own factor
        factor = np.full(3, self.corr) if F is None else np.maximum(F, self.corr)
        std_th = np.sqrt(var_th * chi2 * factor[:, None])
        h = 1e-3                                                               # profile curvature of SSE
        curv = (self._solve(dip + h)[1] - 2 * sse + self._solve(dip - h)[1]) / h ** 2
        std_dip = float(np.sqrt(2.0 * var_scale / curv)) if curv > 0 else float("inf")
        if not self.estimate_dip:
            std_dip = float(np.deg2rad(self.cal0.std.get("dip_deg", 0.0))) if self.cal0.std else 0.0
        std = {"D": std_th[:, :3], "o": std_th[:, 3], "dip_deg": float(np.rad2deg(std_dip))}
        self.current = replace(self.current, D=theta[:3].T.copy(), o=theta[3].copy(),
                               dip_deg=float(np.rad2deg(dip)), std=std)
        self.history.append(self._row(t, self.current, std))
        return self.current

    def _row(self, t: float, cal: Calibration, std) -> dict:
        return {"t": float(t), "D": cal.D.tolist(), "o": cal.o.tolist(), "dip_deg": float(cal.dip_deg),
                "std": None if std is None else {"D": np.asarray(std["D"]).tolist(), "o": np.asarray(std["o"]).tolist(),
                                                  "dip_deg": std["dip_deg"]},
                "whiteness": None if std is None or self.last_whiteness is None else self.last_whiteness.tolist(),
                "std_white": None if std is None or self.std_white is None else
                {k: np.asarray(v).tolist() for k, v in self.std_white.items()},
                "samples": float(self.n), "rejected": int(self.rejected)}
