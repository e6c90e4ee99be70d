"""The magnetometer as a heading sensor: every calibrated field sample constrains only the rotation
about the vertical, leaving tilt to the accelerometer (used once the calibration θ is known).

With the field calibrated, m_j = D⁻¹(y_j − o) in the inertial axes, and sample j attached to keyframe k
(nRb_j = R_k ΔR_j), the field seen in the navigation frame is m_n,j = R_k ΔR_j m_j. Its heading

    ψ_j = atan2(m_n,j,y, m_n,j,x)          (0 when the horizontal field lies along nav x, DESIGN.md)

is the residual. A rotation φ about the navigation vertical turns every heading by φ, and the
perturbation R_k Exp(ξ) is the navigation-frame rotation R_k ξ, so the Jacobian is taken along the
vertical only:

    ∂ψ_j/∂ξ = e_zᵀ R_k                       (tilt directions get no information from the field)

Its noise is the field's direction noise seen in the horizontal plane: σ_ψ,j = σ_m / |m_n,h,j|.

This is the smoothing counterpart of the "heading-only" magnetometer update of attitude filters (the
correction projected onto the vertical axis). It is a deliberate decoupling, not the gradient of the
cost: ψ_j also moves with tilt (by tan δ per radian of roll at dip δ), and no function of the rotation
has e_zᵀ R_k as its derivative (the vertical direction field on SO(3) is not integrable), so the solver
takes tilt from the accelerometer and gyro while the field steers only the heading.
Why: the field's residual errors in a room are slow and mostly vertical (dip) and along the field
(see imugraph.calibration.field_perturbation); in the full 3-D residual they tilt the estimate, while
the accelerometer knows tilt far better. A filter that takes tilt from gravity alone (VQF) does the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.robust import QUADRATIC, Kernel


@dataclass
class HeadingBlock:
    """Calibrated field samples (M, 3) with their keyframe (M,), ΔR (M, 3, 3) and direction noise σ_m."""

    kf: np.ndarray
    kRb: np.ndarray
    m_cal: np.ndarray
    sigma_m: float
    n_keyframes: int
    kernel: Kernel = QUADRATIC
    weight_floor: np.ndarray | None = None

    def _rotations(self, values: gtsam.Values) -> np.ndarray:
        return np.stack([values.atRot3(keys.rot(k)).matrix() for k in range(self.n_keyframes)])

    def residuals(self, nRk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened heading residuals (M,) and σ_ψ (M,)."""
        m_n = np.einsum("mij,mj->mi", nRk[self.kf], np.einsum("mij,mj->mi", self.kRb, self.m_cal))
        h = np.maximum(np.hypot(m_n[:, 0], m_n[:, 1]), 1e-3)
        sigma = self.sigma_m / h
        return np.arctan2(m_n[:, 1], m_n[:, 0]) / sigma, sigma

    def _weights(self, r: np.ndarray) -> np.ndarray:
        w = self.kernel.weight(np.abs(r))
        return w if self.weight_floor is None else w * self.weight_floor

    def cost_at(self, nRk: np.ndarray) -> float:
        r, _ = self.residuals(nRk)
        rho = self.kernel.rho(np.abs(r))
        return float(np.sum(rho if self.weight_floor is None else rho * self.weight_floor))

    def cost(self, values: gtsam.Values) -> float:
        return self.cost_at(self._rotations(values))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """One rank-1 HessianFactor per keyframe: G = (Σ w/σ²) a aᵀ, g = −(Σ w r/σ) a, a = R_kᵀ e_z."""
        nRk = self._rotations(values)
        r, sigma = self.residuals(nRk)
        w = self._weights(r)
        K = self.n_keyframes
        info = np.bincount(self.kf, weights=w / sigma**2, minlength=K)
        grad = np.bincount(self.kf, weights=w * r / sigma, minlength=K)
        f = np.bincount(self.kf, weights=w * r**2, minlength=K)
        a = nRk[:, 2, :]                                           # R_kᵀ e_z (third row of R_k)
        gfg = gtsam.GaussianFactorGraph()
        for k in np.flatnonzero(info > 0):
            gfg.push_back(gtsam.HessianFactor(keys.rot(int(k)), info[k] * np.outer(a[k], a[k]),
                                              -grad[k] * a[k], float(f[k])))
        return gfg


def heading_only_rotations(session, opt, pre, values, noise, g_used, theta, bias, seg, mag_state, velocity):
    """Keyframe orientations with θ known and the field used as heading only (HeadingBlock), from the joint
    solution `values` (Options.heading_only_orientation; calibration.ml's last stage). velocity: the ML loop's
    VelocityModel (or None)."""
    from imugraph.factors.theta import unpack_theta
    from imugraph.graphs.single_imu import build_problem, keyframe_rotations
    from imugraph.graphs.solver import optimize

    K = len(pre.kf_samples)
    nRk = keyframe_rotations(values, K)
    no_mag = np.full_like(session.mag, np.nan)
    stage = build_problem(pre, session.acc, no_mag, noise, g_used, nRk, bias, theta, estimate_theta=False,
                          bias_prior_sigma=opt.bias_prior_sigma, acc_kernel=opt.acc_kernel,
                          bias_segment=seg, bias_rw_sigma=opt.bias_rw, velocity=velocity, dt=session.dt)
    D, o, _ = unpack_theta(theta)
    y = mag_state["y"]
    ok = np.all(np.isfinite(y), axis=1)
    scale = float(np.cbrt(abs(np.linalg.det(D))))
    heading = HeadingBlock(pre.sample_kf[ok], pre.kRb[ok], np.linalg.solve(D, (y[ok] - o).T).T,
                           float(np.sqrt(np.mean(np.asarray(noise.mag) ** 2))) / scale, K, opt.mag_kernel,
                           None if mag_state["w"] is None else mag_state["w"][ok])
    out, _ = optimize(stage.graph, stage.blocks + [heading], stage.values, stage.ordering, opt.solver)
    return keyframe_rotations(out, K)
