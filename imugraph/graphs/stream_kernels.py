"""Per-keyframe arithmetic of the stream (imugraph.graphs.stream) written for one interval: scalar Python
instead of numpy calls whose fixed cost (1–20 µs each) dominates at 3×3 and ≈ 30 rows (issue 3, θ-state
speed; tests/test_stream_kernels.py compares each with the general function it replaces).

- `split_noise_one`: `cpp_velocity.split_noise` for one interval. The rotation rows' square-root information
  is the upper Cholesky factor U of Σ_ΔR⁻¹,

      Σ_ΔR⁻¹ = adj(Σ_ΔR) / det Σ_ΔR = L Lᵀ (L lower: Cholesky),   U = Lᵀ                          (1)

  the 3×3 inverse by cofactors and the Cholesky factor entry by entry (numpy's inv + cholesky: ≈ 17 µs);
  the velocity rows' precisions (0, 0, 0, 1/σ_p², …, 1/σ_Δv², …) as in split_noise, Huber-robust.
- `StepBlocks`: the Gauss–Markov blocks of the bounded-velocity factor (stream_interval.gauss_markov_factor) and
  of the field-perturbation step (stream_field.field_step_factor) depend on the interval length Δt_k only,
  which takes a handful of values in a stream: computed once per distinct Δt_k (bounded cache) and reused.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from imugraph.factors.field import field_sigmas
from imugraph.graphs.cpp_velocity import SIGMA_POS, robust

_EYE3, _ZERO3, _UNIT3 = np.eye(3), np.zeros(3), gtsam.noiseModel.Unit.Create(3)


def rot_sqrt_info(cov: np.ndarray) -> np.ndarray:
    """(9, 9) square-root information of the IMU residual's rotation rows: U of eq. (1) in [:3, :3], zero
    elsewhere (`split_noise`'s first model). cov: (3, 3) symmetric positive definite Σ_ΔR."""
    (a, b, c), (d, e, f), (g, h, i) = cov.tolist()
    # cofactors (adjugate = cofactor matrixᵀ); Σ symmetric up to rounding: the lower triangle, as cholesky reads
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    p11, p21, p31 = A / det, B / det, C / det                           # first column of Σ⁻¹
    p22, p32 = (a * i - c * g) / det, (b * g - a * h) / det
    p33 = (a * e - b * d) / det
    l11 = math.sqrt(p11)                                                # Σ⁻¹ = L Lᵀ
    l21, l31 = p21 / l11, p31 / l11
    l22 = math.sqrt(p22 - l21 * l21)
    l32 = (p32 - l31 * l21) / l22
    l33 = math.sqrt(p33 - l31 * l31 - l32 * l32)
    out = np.zeros((9, 9))
    out[:3, :3] = ((l11, l21, l31), (0.0, l22, l32), (0.0, 0.0, l33))   # U = Lᵀ
    return out


def split_noise_one(cov: np.ndarray, sigma_dv: float, huber_k: float | None) -> tuple:
    """(rotation-rows model, Huber velocity-rows model) of one interval's 9-row IMU residual, as
    `cpp_velocity.split_noise(cov[None], [sigma_dv], huber_k)[0]`."""
    p_v = 1.0 / float(sigma_dv) ** 2
    p_p = 1.0 / SIGMA_POS**2
    prec = np.array([0.0, 0.0, 0.0, p_p, p_p, p_p, p_v, p_v, p_v])
    return (gtsam.noiseModel.Gaussian.SqrtInformation(rot_sqrt_info(cov)),
            robust(gtsam.noiseModel.Diagonal.Precisions(prec), huber_k))


def velocity_blocks(dt_k: float, sigma_v: float, tau_v: float) -> tuple:
    """(A_k, A_{k+1}) of (v_{k+1} − φ v_k)/σ_w, φ = exp(−Δt/τ_v), σ_w = σ_v √(1 − φ²) (scalar arithmetic)."""
    phi = math.exp(-float(dt_k) / max(tau_v, 1e-9))
    sig_w = sigma_v * math.sqrt(max(1.0 - phi * phi, 1e-12))
    return (-phi / sig_w) * _EYE3, _EYE3 / sig_w


def field_blocks(dt_k: float, sig_d: np.ndarray, tau_d: float) -> tuple:
    """(A_k, A_{k+1}) of (d_{k+1} − φ d_k)/σ_w per nav axis, φ = exp(−Δt/τ_d), σ_w = σ_d √(1 − φ²); sig_d from
    `field_sigmas`."""
    phi = math.exp(-float(dt_k) / max(tau_d, 1e-9))
    sig_w = math.sqrt(max(1.0 - phi * phi, 1e-12)) * sig_d
    return np.diag(-phi / sig_w), np.diag(1.0 / sig_w)


class StepBlocks:
    """Blocks (A_k, A_{k+1}) of the two Gauss–Markov steps of an interval, by Δt_k (at most `size` cached):

        velocity:  (v_{k+1} − φ v_k)/σ_w,  φ = exp(−Δt/τ_v), σ_w = σ_v √(1 − φ²)    (stream_interval.gauss_markov_factor)
        field:     (d_{k+1} − φ d_k)/σ_w,  φ = exp(−Δt/τ_d), σ_w = σ_d √(1 − φ²)    (stream_field eq. 2, per nav axis)
    """

    def __init__(self, sigma_v: float, tau_v: float, sigma_d=None, tau_d: float | None = None, size: int = 64):
        self.sigma_v, self.tau_v, self.tau_d, self.size = float(sigma_v), float(tau_v), tau_d, size
        self.sig_d = None if sigma_d is None else field_sigmas(sigma_d)
        self._vel: dict = {}
        self._field: dict = {}

    def velocity(self, dt_k: float) -> tuple:
        got = self._vel.get(dt_k)
        if got is None:
            got = velocity_blocks(dt_k, self.sigma_v, self.tau_v)
            self._keep(self._vel, dt_k, got)
        return got

    def field(self, dt_k: float) -> tuple:
        got = self._field.get(dt_k)
        if got is None:
            got = field_blocks(dt_k, self.sig_d, self.tau_d)
            self._keep(self._field, dt_k, got)
        return got

    def _keep(self, cache: dict, dt_k: float, blocks: tuple) -> None:
        if len(cache) >= self.size:
            cache.clear()
        cache[dt_k] = blocks


def linear_step(key_k: int, key_next: int, blocks: tuple) -> gtsam.LinearContainerFactor:
    """The exact linear factor A_k x_k + A_{k+1} x_{k+1} ~ N(0, I) on two 3-vector keys (linearised at 0)."""
    jf = gtsam.JacobianFactor(key_k, blocks[0], key_next, blocks[1], _ZERO3, _UNIT3)
    lin = gtsam.Values()
    lin.insert(key_k, _ZERO3)
    lin.insert(key_next, _ZERO3)
    return gtsam.LinearContainerFactor(jf, lin)
