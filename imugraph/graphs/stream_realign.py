"""Realignment about the magnetic field after a long sample drop (StreamOptions.gap_realign_s; task G, issue 3).

Why. Over a drop of τ the held gyro rate can turn the post-gap keyframe far (BROAD 06, 0.5 s: 169°) from the
truth. The magnetometer restores two axes; the rotation α about the field vector n̂ is left to gravity, which
the stream sees only through the velocity rows. Rotating the gravity direction e_z about n̂ (dip δ) by α tilts it
by 2·asin(sin(α/2)·cos δ): the tilt is stationary (a maximum) at α = π. From the gyro's α ≈ 160° the gradient of
every gravity term is nearly zero, so Gauss–Newton steps are tiny, the velocity states absorb the leaked gravity
(|v| 0.5 → 12 m/s in 5 s on 06, benchmarks/g3_tilt.py --trace) and the window's marginal priors carry the wrong
basin on. A local method cannot leave it; a one-dimensional global solve can.

The model. Over the first W seconds after the gap the integrated specific force, in the post-gap keyframe g's
frame through the gyro only (no estimate), is

    u_g = Σ_j gR_j Δv_j,     Δv_j = Σ_i jR_i a_i Δt_i        (stream_interval eq. 3)                    (R1)

and in the nav frame nR_g u_g = v(t_g + W) − v(t_g) + g W e_z. With the bounded velocity process the first term
is ≈ 0 (std √2 σ_v), so nR_g u_g points up. Only α about n̂ is free (the magnetometer fixes the rest), so

    α* = atan2(n̂ · (u⊥ × e_z⊥), u⊥ · e_z⊥),   u = R̂ u_g,  x⊥ = x − (n̂·x) n̂                            (R2)
    σ_α = √2 σ_v / |u⊥|                                                                                   (R3)

(R3) is the angle that a velocity change of √2 σ_v makes seen across u⊥. When |α*| > gate · σ_α (the data
disagree with the current estimate beyond their own noise):

- the gap's rotation rows (the held rate's ΔR, eq. G1) are removed from the graph: the test rejected them;
- the newest keyframe gets a one-axis pin at Exp(α* n̂)·R̂ (σ gap_realign_pin_deg about n̂ only: body axis
  R̂ᵀ n̂, ε elsewhere), removed after gap_realign_hold updates, every one of them relinearising (iSAM2's
  deferred, partial check otherwise leaves the post-gap keyframes linearised in the old basin);
- with gap_realign_keep, also a lasting one-axis prior at the same rotation with σ_α (it reuses data the
  velocity rows use: a double count, loose at ≈ 13–15° for W = 1 s at a dip of 72°).

Measured (docs/gaps.md, "Task G"): the test is right (06: α* = 142°, the predicted keyframe's tilt 33.5° →
4.0° after the rotation), but after the pin leaves the stream returns towards the old tilt: the post-gap
velocities have absorbed the leaked gravity (a phantom velocity), and with the precise velocity rows and the
window's marginal prior only a tilt error can decelerate it. The option is a partial fix, not a cure.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from imugraph.graphs.cpp_velocity import pose_key

_EPS_INFO = 1e-9       # information on the unconstrained axes of the anchor (rad⁻², m⁻²): keeps it positive definite


class GapRealign:
    """The running sum (R1) of one post-gap window, started at keyframe g."""

    def __init__(self, window_s: float):
        self.window_s = float(window_s)
        self.gR = np.eye(3)        # rotation of the current keyframe's frame into keyframe g's frame (gyro only)
        self.u = np.zeros(3)       # u_g of (R1), m/s
        self.T = 0.0

    def add(self, dv: np.ndarray, delta_R: np.ndarray, dt_k: float) -> bool:
        """Fold one interval (its Δv in its keyframe's frame, its ΔR, its Δt); True once W seconds are in."""
        self.u += self.gR @ np.asarray(dv, float)
        self.gR = self.gR @ np.asarray(delta_R, float)
        self.T += float(dt_k)
        return self.T >= self.window_s

    def solve(self, nRnext: np.ndarray, n_hat: np.ndarray, sigma_v: float) -> tuple[float, float]:
        """(α*, σ_α) of (R2), (R3), given the predicted rotation of the keyframe that closes the window."""
        u = nRnext @ self.gR.T @ self.u                   # nR_g u_g, nR_g = nR_next · gR_nextᵀ
        n = np.asarray(n_hat, float) / np.linalg.norm(n_hat)
        z = np.array([0.0, 0.0, 1.0])
        u_p, z_p = u - (n @ u) * n, z - (n @ z) * n
        alpha = math.atan2(float(n @ np.cross(u_p, z_p)), float(u_p @ z_p))    # (R2)
        return alpha, math.sqrt(2.0) * float(sigma_v) / max(float(np.linalg.norm(u_p)), 1e-9)   # (R3)


def anchor_factor(key: int, nRk: np.ndarray, p: np.ndarray, n_hat: np.ndarray, alpha: float, sigma: float):
    """PriorFactorPose3 on `key` at Exp(α n̂)·nRk, informative only about n̂ (σ); the translation is free."""
    n = np.asarray(n_hat, float) / np.linalg.norm(n_hat)
    R_anchor = gtsam.Rot3.Expmap(alpha * n).matrix() @ np.asarray(nRk, float)
    b = R_anchor.T @ n                                       # the nav axis n̂ in the body frame (Pose3's tangent)
    info = np.eye(6) * _EPS_INFO
    info[:3, :3] += np.outer(b, b) / sigma**2
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(gtsam.Rot3(R_anchor), np.asarray(p, float)),
                                  gtsam.noiseModel.Gaussian.Information(info))


class GapRealignMixin:
    """StreamSmoother's side of the realignment (options gap_realign_*): the window after a gap, the test,
    the temporary pin and the rejected gap rotation rows. Chain lag and iSAM2 only (factor removal); with
    gtsam's fixed-lag smoothers the test is logged but never applied."""

    def _init_realign(self) -> None:
        self._realign = None          # the open window (GapRealign), with .gap_index: the gap's rotation rows
        self._anchor = None           # [iSAM2 index, updates left] of the temporary anchor
        self._remove_next: list = []  # iSAM2 indices to remove in the next update
        self.realign_log: list = []   # per window: (keyframe, α* °, σ_α °, applied, predicted nRb)

    def _realign_step(self, graph, values, k: int, ends_in_gap: bool, interval: tuple, R_next: np.ndarray,
                      rot_at: int) -> None:
        """Called in `_close` before the update of keyframe k+1 (graph: its new factors; rot_at: the position in
        it of interval k's rotation rows)."""
        usable = self._chain or self.opt.lag_s is None
        if self._realign is not None and self._realign.add(*interval):
            alpha, sig = self._realign.solve(R_next, self.cal.n_mag, self._sig_v)
            apply = usable and abs(alpha) > self.opt.gap_realign_gate * sig
            # (keyframe k+1 that closes the window; α* °; σ_α °; applied; its predicted nRb, for benchmarks)
            self.realign_log.append((k + 1, math.degrees(alpha), math.degrees(sig), apply, np.asarray(R_next).copy()))
            if apply:
                isam = self._isam()
                n_before = isam.getFactorsUnsafe().size()          # new factors are appended
                if isam.getFactorsUnsafe().exists(self._realign.gap_index):
                    # the gyro's rotation across the gap is rejected by the test: its rows leave the graph
                    self._remove_next.append(self._realign.gap_index)
                self._anchor = [[n_before + graph.size()], self.opt.gap_realign_hold]
                p = values.atPose3(pose_key(k + 1)).translation()
                graph.add(anchor_factor(pose_key(k + 1), R_next, p, self.cal.n_mag, alpha,
                                        math.radians(self.opt.gap_realign_pin_deg)))
                if self.opt.gap_realign_keep:        # the observation (R2) with its σ_α (R3) stays
                    graph.add(anchor_factor(pose_key(k + 1), R_next, p, self.cal.n_mag, alpha, sig))
            self._realign = None
        if ends_in_gap and usable:                      # a window starts at the post-gap keyframe k+1
            self._realign = GapRealign(self.opt.gap_realign_s)
            self._realign.gap_index = self._isam().getFactorsUnsafe().size() + rot_at

    def _realign_removals(self) -> tuple:
        """(factor indices the coming update removes, relinearise in it): a rejected gap's rotation rows, an
        anchor whose gap_realign_hold updates are over. While an anchor holds, and at its removal, every update
        relinearises: iSAM2's deferred, partial check otherwise leaves the post-gap keyframes linearised in the
        old basin (measured: back from 7° to 24° tilt in one update after the anchor left)."""
        out, self._remove_next = tuple(self._remove_next), []
        force = self._anchor is not None
        if self._anchor is not None:
            self._anchor[1] -= 1
            if self._anchor[1] < 0:
                out, self._anchor = out + tuple(self._anchor[0]), None
        return out, force

