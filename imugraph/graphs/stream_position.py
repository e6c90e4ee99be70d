"""A bounded keyframe position in the stream (StreamOptions.position_sigma; task K, issue 3): the batch's (P1)
(imugraph.graphs.velocity_block, results_issue2 "Session 16", H11) in the stream window, marginalised with the
keyframe like its velocity.

Why. After a long sample drop the stream can keep a wrong tilt for tens of seconds (docs/gaps.md: BROAD 06,
3 × 0.5 s drops, 38° filtered). The wrong tilt ε leaks g·ε into the horizontal specific force, the precise
velocity rows carry it into the velocities as a phantom velocity, and the window's marginal prior hands the
phantom on. The bounded-velocity process is the only thing that sees it, and it sees only the velocity's level
(σ_v), not its integral. A position that integrates the velocity sees it quadratically in time: a tilt error ε
held T seconds moves the position by ½ g ε T² (30° for 2 s: 10 m), and the sensor stays within reach.

The model (per keyframe interval k → k+1, nav frame, m; key `position_key`, symbol "p"):

    (p_{k+1} − p_k − v_k Δt_k) / σ_kin = 0 ± 1                         (kinematics, Euler)       (K1)
    (p_{k+1} − φ_k p_k) / σ_w = 0 ± 1,   φ_k = exp(−Δt_k/τ_p),   σ_w = σ_p √(1 − φ_k²)           (K2)
    p_0 ~ N(0, σ_p² I)                                                   (stationary start)        (K3)

(K1)–(K2) are one exact linear factor on (p_k, p_{k+1}, v_k) (6 rows), (K3) one on p_0. The Euler step's error
against the true position, Σ(v_{k+1} − v_k)Δt/2, telescopes (≤ |v|Δt/2), so σ_kin is small (1 mm, as the batch).
Over a gap Δt_k holds the missing time: (K1) integrates the velocity across it and (K2)'s step widens with it.
The Pose3 translation of the keyframes stays what it was (free: cpp_velocity); this is a separate state.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from imugraph import keys
from imugraph.graphs.velocity_block import POSITION_KIN_SIGMA, pos_key

_EYE3, _ZERO3, _UNIT6 = np.eye(3), np.zeros(3), gtsam.noiseModel.Unit.Create(6)


position_key = pos_key   # keyframe k's bounded position p_k (Vector3, nav frame, m): the batch's key


def position_blocks(dt_k: float, sigma_p: float, tau_p: float, sigma_kin: float = POSITION_KIN_SIGMA) -> tuple:
    """(A_pk, A_pk+1, A_vk) (6×3 each) of (K1) stacked over (K2), whitened."""
    phi = math.exp(-float(dt_k) / max(float(tau_p), 1e-9))
    sig_w = float(sigma_p) * math.sqrt(max(1.0 - phi * phi, 1e-12))
    A_p0 = np.vstack([-_EYE3 / sigma_kin, (-phi / sig_w) * _EYE3])
    A_p1 = np.vstack([_EYE3 / sigma_kin, _EYE3 / sig_w])
    A_v0 = np.vstack([(-float(dt_k) / sigma_kin) * _EYE3, np.zeros((3, 3))])
    return A_p0, A_p1, A_v0


def position_step(k: int, dt_k: float, sigma_p: float, tau_p: float) -> gtsam.LinearContainerFactor:
    """(K1)–(K2) of interval k as one exact linear factor on (p_k, p_{k+1}, v_k) (linearised at 0)."""
    A_p0, A_p1, A_v0 = position_blocks(dt_k, sigma_p, tau_p)
    pk, pn, vk = position_key(k), position_key(k + 1), keys.vel(k)
    jf = gtsam.JacobianFactor(pk, A_p0, pn, A_p1, vk, A_v0, np.zeros(6), _UNIT6)
    lin = gtsam.Values()
    for key in (pk, pn, vk):
        lin.insert(key, _ZERO3)
    return gtsam.LinearContainerFactor(jf, lin)


def position_start(sigma_p: float) -> gtsam.PriorFactorVector:
    """(K3): p_0 ~ N(0, σ_p² I)."""
    return gtsam.PriorFactorVector(position_key(0), _ZERO3, gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_p)))


class PositionMixin:
    """StreamSmoother's side of the bounded position (options position_sigma, position_tau): keyframe 0's start
    (K3) and each interval's (K1)–(K2), with the start value p_{k+1} = p_k + v_k Δt_k (exact factors: the start
    value does not change the solution). State: self._pos_on, self._p_pos (the latest p_k start value)."""

    def _init_position(self) -> None:
        sigma = self.opt.position_sigma
        self._pos_on = sigma is not None
        if self._pos_on and not (np.isfinite(sigma) and sigma > 0 and self.opt.position_tau > 0):
            from imugraph.errors import SessionError
            raise SessionError("stream", "position_sigma", repr(sigma), "a positive σ_p in m (and position_tau > 0)")
        self._p_pos = np.zeros(3)

    def _position_start(self, graph, values, stamps) -> None:
        graph.add(position_start(self.opt.position_sigma))
        values.insert(position_key(0), np.zeros(3))
        stamps[position_key(0)] = 0.0

    def _position_interval(self, graph, values, stamps, k: int, dt_k: float, t_next: float) -> None:
        """Interval k → k+1: (K1)–(K2), and p_{k+1}'s start value from the latest v_k."""
        graph.add(position_step(k, dt_k, self.opt.position_sigma, self.opt.position_tau))
        self._p_pos = self._p_pos + np.asarray(self._v, float) * dt_k
        values.insert(position_key(k + 1), self._p_pos)
        stamps[position_key(k + 1)] = t_next
