"""All accelerometer and magnetometer samples of a session as one vectorised block of the graph.

The block evaluates the models of `imugraph.factors.accelerometer` and `imugraph.factors.magnetometer`
for every sample at once (numpy), applies per-sample robust weights (`imugraph.factors.robust`), and
hands GTSAM one `HessianFactor` per keyframe on (R_k, θ):

    G11 = Σ_j w_j J_Rᵀ J_R,  G12 = Σ_j w_j J_Rᵀ J_θ,  G22 = Σ_j w_j J_θᵀ J_θ,
    g1  = −Σ_j w_j J_Rᵀ r_j, g2  = −Σ_j w_j J_θᵀ r_j, f = Σ_j w_j |r_j|²

(whitened residuals r_j and Jacobians J; GTSAM's HessianFactor error is ½(f − 2xᵀg + xᵀGx)).
This is the same linearisation GTSAM would compute from one CustomFactor per keyframe, at a fraction
of the cost: no Python callback per factor (see GTSAM_NOTES.md: callbacks dominate batch cost).

All six are blocks of one Gram matrix per keyframe, Σ_j A_jᵀA_j of the weighted rows
A_j = w_j^½ Σ^−½ [J'_R,j | J_θ,j | e_j], accumulated as one batched matrix product over the samples of
each keyframe. The rotation Jacobian factors as J_R,j = J'_R,j [v_k]× with a per-keyframe right factor
(∂e/∂ξ = D ΔR_jᵀ [R_kᵀ n]×, g ΔR_jᵀ [R_kᵀ e_z]×), which is applied to the keyframe sums, not to every sample.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.accelerometer import accelerometer_residual, accelerometer_rows
from imugraph.factors.magnetometer import magnetometer_residual, magnetometer_rows
from imugraph.factors.robust import QUADRATIC, Kernel
from imugraph.factors.theta import THETA_DIM
from imugraph.graphs.solver import state_keys

CHUNK = 4096        # samples linearised at a time (whole keyframes): their rows stay in cache


@dataclass
class ChannelData:
    """Samples of one channel attached to keyframes: rows of `values` with their keyframe and ΔR."""

    kf: np.ndarray        # (M,) keyframe index of each sample
    kRb: np.ndarray       # (M, 3, 3)
    values: np.ndarray    # (M, 3) measurements
    sigma: np.ndarray     # (3,) per-axis std
    kernel: Kernel = QUADRATIC
    weight_floor: np.ndarray | None = None   # optional fixed extra weights (M,) in [0, 1]


@dataclass
class MeasurementBlock:
    """The accelerometer and magnetometer channels of one session, for K keyframes."""

    n_keyframes: int
    acc: ChannelData | None
    mag: ChannelData | None
    g: float = 9.81
    use_theta: bool = True
    use_acc: bool = True        # False: acc residuals are reported but not in the cost (velocity model)
    with_field: bool = False    # per-keyframe nav-field perturbation keys d_k (imugraph.factors.field)
    field_offsets: np.ndarray | None = None   # (K, 3) current d_k, used by every residual/linearisation
    _last: dict = field(default_factory=dict, repr=False)

    # ---- residuals -------------------------------------------------------------------------------
    def residuals(self, nRk: np.ndarray, theta: np.ndarray, in_cost_only: bool = False) -> dict:
        """Whitened residuals per channel: {"acc": (M, 3), "mag": (M, 3)} at keyframe rotations nRk
        (in_cost_only: skip a channel that is reported but not in the cost)."""
        out = {}
        if self.acc is not None and (self.use_acc or not in_cost_only):
            out["acc"] = self.raw_residuals("acc", nRk, theta) / self.acc.sigma
        if self.mag is not None:
            out["mag"] = self.raw_residuals("mag", nRk, theta) / self.mag.sigma
        return out

    def raw_residuals(self, name: str, nRk: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Residuals h − y (M, 3) of channel `name`, in its own unit (not whitened)."""
        ch = getattr(self, name)
        if name == "acc":
            return accelerometer_residual(ch.kRb, ch.kf, nRk, ch.values, self.g)
        return magnetometer_residual(ch.kRb, ch.kf, nRk, theta, ch.values, self.field_offsets)

    def cost(self, nRk: np.ndarray, theta: np.ndarray) -> float:
        """Σ ρ(|r_j|) over both channels (GTSAM's ½|r|² for the quadratic kernel)."""
        total = 0.0
        for name, r in self.residuals(nRk, theta, in_cost_only=True).items():
            ch = getattr(self, name)
            rho = ch.kernel.rho(np.linalg.norm(r, axis=1))
            if ch.weight_floor is not None:
                rho = rho * ch.weight_floor
            total += float(rho.sum())
        return total

    # ---- linearisation ---------------------------------------------------------------------------
    def channel_rows(self, name: str, nRk: np.ndarray, theta: np.ndarray, with_theta: bool = True,
                     rows: slice = slice(None), k0: int = 0):
        """Unwhitened rows X (M, 3, C) = [J'_R | J_θ (if with_theta) | e] of channel `name` and the
        per-keyframe right factor V (K, 3, 3) of its rotation Jacobian (J_R,j = J'_R,j · V[kf_j]).

        rows: a slice of the channel's samples; k0: their keyframe indices are taken relative to k0
        (nRk then holds keyframes k0, k0+1, …)."""
        ch = getattr(self, name)
        kf = ch.kf[rows] - k0
        if name == "acc":
            return accelerometer_rows(ch.kRb[rows], kf, nRk, ch.values[rows], self.g)
        off = None if self.field_offsets is None else self.field_offsets[k0:k0 + len(nRk)]
        X, V = magnetometer_rows(ch.kRb[rows], kf, nRk, theta, ch.values[rows], off)
        return (X if with_theta else X[:, :, [0, 1, 2, -1]]), V

    def channel_gram(self, name: str, nRk: np.ndarray, theta: np.ndarray, with_theta: bool = True):
        """Per-keyframe Gram G (K, C, C) of the robust-weighted, whitened rows A_j = w_j^½ Σ^−½ [J'_R | J_θ | e]_j
        and the right factor V (K, 3, 3) (see `channel_rows`).

        Computed over runs of whole keyframes of about CHUNK samples, so that the rows stay in cache."""
        ch = getattr(self, name)
        K = self.n_keyframes
        bounds = np.searchsorted(ch.kf, np.arange(K + 1)) if _is_sorted(ch.kf) else None
        if bounds is None or len(ch.kf) <= CHUNK:
            X, V = self.channel_rows(name, nRk, theta, with_theta)
            return _gram_by(ch.kf, self._whiten(ch, X), K), V
        G, V = None, None
        k = 0
        while k < K:
            k1 = int(np.searchsorted(bounds, bounds[k] + CHUNK, side="right")) - 1
            k1 = min(max(k1, k + 1), K)
            rows = slice(int(bounds[k]), int(bounds[k1]))
            X, Vc = self.channel_rows(name, nRk[k:k1], theta, with_theta, rows, k)
            Gc = _gram_by(ch.kf[rows] - k, self._whiten(ch, X, rows), k1 - k)
            if G is None:
                G, V = np.zeros((K,) + Gc.shape[1:]), np.zeros((K, 3, 3))
            G[k:k1], V[k:k1] = Gc, Vc
            k = k1
        return G, V

    @staticmethod
    def _whiten(ch: ChannelData, X: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
        """X scaled in place to w_j^½ Σ^−½ X_j (robust weight from the whitened residual in the last column)."""
        w = ch.kernel.weight(np.linalg.norm(X[:, :, -1] / ch.sigma, axis=1))
        if ch.weight_floor is not None:
            w = w * ch.weight_floor[rows]
        X *= (np.sqrt(w)[:, None] / ch.sigma[None, :])[:, :, None]
        return X

    @staticmethod
    def _blocks(G: np.ndarray, V: np.ndarray):
        """Normal-equation blocks of one channel from its Gram (see `channel_gram`):
            G11 = Vᵀ [Σ J'ᵀJ'] V,  G12 = Vᵀ Σ J'ᵀJ_θ,  G22 = Σ J_θᵀJ_θ,  g = −[Vᵀ Σ J'ᵀr; Σ J_θᵀr],  f = Σ rᵀr
        Returns G11, G12, G22, g1, g2, f (the θ terms None when G has no θ columns)."""
        Vt = np.transpose(V, (0, 2, 1))
        G11 = Vt @ G[:, :3, :3] @ V
        g1 = -(Vt @ G[:, :3, -1:])[:, :, 0]
        f = G[:, -1, -1].copy()
        if G.shape[2] == 4:
            return G11, None, None, g1, None, f
        return G11, Vt @ G[:, :3, 3:-1], G[:, 3:-1, 3:-1], g1, -G[:, 3:-1, -1], f

    def channel_blocks(self, name: str, nRk: np.ndarray, theta: np.ndarray, with_theta: bool = True):
        """G11, G12, G22, g1, g2, f of one channel (θ terms None without θ)."""
        return self._blocks(*self.channel_gram(name, nRk, theta, with_theta))

    def hessian_blocks(self, nRk: np.ndarray, theta: np.ndarray):
        """Per-keyframe blocks (G11 (K,3,3), G12 (K,3,13), G22 (K,13,13), g1 (K,3), g2 (K,13), f (K,))."""
        K = self.n_keyframes
        G11 = np.zeros((K, 3, 3)); g1 = np.zeros((K, 3)); f = np.zeros(K)
        G12 = np.zeros((K, 3, THETA_DIM)); G22 = np.zeros((K, THETA_DIM, THETA_DIM)); g2 = np.zeros((K, THETA_DIM))
        if self.acc is not None and self.use_acc:
            a11, _, _, a1, _, af = self.channel_blocks("acc", nRk, theta, with_theta=False)
            G11 += a11; g1 += a1; f += af
        if self.mag is not None:
            Gm, V = self.channel_gram("mag", nRk, theta, with_theta=self.use_theta)
            m11, m12, m22, m1, m2, mf = self._blocks(Gm, V)
            G11 += m11; g1 += m1; f += mf
            if self.use_theta:
                G12 += m12; G22 += m22; g2 += m2
            if self.with_field:
                self._last["field"] = self._field_blocks(Gm, V, nRk)
        return G11, G12, G22, g1, g2, f

    def field_information(self, nRk: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(K, 3, 3) whitened magnetometer information of each keyframe's field perturbation d_k (G_dd)."""
        return self._field_blocks(*self.channel_gram("mag", nRk, theta, with_theta=False), nRk)[2]

    @staticmethod
    def _field_blocks(G: np.ndarray, V: np.ndarray, nRk: np.ndarray):
        """Normal-equation blocks of the field perturbation d_k from the magnetometer Gram (J_d = J' R_kᵀ,
        imugraph.factors.field): G_Rd = Vᵀ G'₀₀ R_kᵀ, G_θd = G'_θ₀ R_kᵀ, G_dd = R_k G'₀₀ R_kᵀ,
        g_d = −R_k Σ J'ᵀ r. Returns G_Rd (K,3,3), G_θd (K,13,3) or None, G_dd (K,3,3), g_d (K,3)."""
        Vt = np.transpose(V, (0, 2, 1))
        kRn = np.transpose(nRk, (0, 2, 1))
        G00 = G[:, :3, :3]
        G_Rd = Vt @ G00 @ kRn
        G_dd = nRk @ G00 @ kRn
        g_d = -(nRk @ G[:, :3, -1:])[:, :, 0]
        G_td = None if G.shape[2] == 4 else np.transpose(G[:, :3, 3:-1], (0, 2, 1)) @ kRn
        return G_Rd, G_td, G_dd, g_d

    def linear_factors(self, nRk: np.ndarray, theta: np.ndarray) -> gtsam.GaussianFactorGraph:
        """A GaussianFactorGraph with one HessianFactor per keyframe (two keys when θ is estimated)."""
        G11, G12, G22, g1, g2, f = self.hessian_blocks(nRk, theta)
        gfg = gtsam.GaussianFactorGraph()
        two = self.use_theta and self.mag is not None
        rot = state_keys(keys.rot, self.n_keyframes)
        if self.with_field and self.mag is not None:
            return self._field_factors(gfg, rot, two, G11, G12, G22, g1, g2, f)
        for k in range(self.n_keyframes):
            if two:
                gfg.push_back(gtsam.HessianFactor(rot[k], keys.CALIB, G11[k], G12[k], g1[k], G22[k], g2[k], f[k]))
            else:
                gfg.push_back(gtsam.HessianFactor(rot[k], G11[k], g1[k], f[k]))
        return gfg

    def _field_factors(self, gfg, rot, two, G11, G12, G22, g1, g2, f):
        """One HessianFactor per keyframe on (R_k, θ, d_k), or (R_k, d_k) when θ is fixed."""
        from imugraph.factors.field import field_key

        G_Rd, G_td, G_dd, g_d = self._last.pop("field")
        fk = state_keys(field_key, self.n_keyframes)
        for k in range(self.n_keyframes):
            if two:
                gfg.push_back(gtsam.HessianFactor(rot[k], keys.CALIB, fk[k], G11[k], G12[k], G_Rd[k], g1[k],
                                                  G22[k], G_td[k], g2[k], G_dd[k], g_d[k], f[k]))
            else:
                gfg.push_back(gtsam.HessianFactor(rot[k], fk[k], G11[k], G_Rd[k], g1[k], G_dd[k], g_d[k],
                                                  f[k]))
        return gfg


def _gram_by(index: np.ndarray, X: np.ndarray, n: int) -> np.ndarray:
    """Per-bin Gram matrices Σ_{j: index_j = b} X_jᵀ X_j of rows X (M, r, C) → (n, C, C).

    The samples of each bin are laid out as one (L·r, C) matrix (L = largest bin, zero-padded when the
    bins differ), so the sum of outer products is one batched matrix product instead of M small products
    and a reduction. Keyframe layouts are regular (every bin but the last holds L samples): then X is
    used in place.
    """
    m, r, c = X.shape
    out = np.zeros((n, c, c))
    if m == 0:
        return out
    counts = np.bincount(index, minlength=n)
    L = int(counts.max())
    if n * L > 4 * m + 4096:          # very uneven bins: the padded buffer would be mostly zeros
        np.add.at(out, index, np.transpose(X, (0, 2, 1)) @ X)
        return out
    if not _is_sorted(index):
        order = np.argsort(index, kind="stable")
        index, X = index[order], X[order]
    full = int(np.argmax(counts != L)) if np.any(counts != L) else n     # leading bins holding L samples
    if full and index[full * L - 1] == full - 1:
        B = X[:full * L].reshape(full, L * r, c)
        np.matmul(np.transpose(B, (0, 2, 1)), B, out=out[:full])
        if full == n:
            return out
        index, X = index[full * L:], X[full * L:]
        sub = _gram_by(index - full, X, n - full)
        out[full:] = sub
        return out
    pos = np.arange(len(index)) - (np.cumsum(counts) - counts)[index]
    buf = np.zeros((n, L, r, c))
    buf[index, pos] = X
    B = buf.reshape(n, L * r, c)
    return np.matmul(np.transpose(B, (0, 2, 1)), B, out=out)


def _is_sorted(index: np.ndarray) -> bool:
    return bool(np.all(index[1:] >= index[:-1])) if len(index) > 1 else True
