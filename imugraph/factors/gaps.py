"""Samples that never arrived: what the preintegration assumes over a gap, and how much it trusts it.

A time step Δt_j longer than 1.5 nominal steps T holds τ_j = Δt_j − T of missing time (a wireless packet lost,
a logger stall). The preintegration holds the last gyro rate and specific force across it (the only values it
has); their true change over τ is unknown. It is modelled as a random walk of density q (a Wiener process W),
whose integral over the gap is off by

    Var[∫₀^τ W(s) ds] = q² τ³ / 3   per axis                                                      (G1)

added to the rotation increment's covariance (q_ω, rad/s^1.5) and to the velocity increment's (q_a, m/s^2.5).
Without it the held sample was trusted like measured samples: three 0.5 s drops in BROAD 01 (2.3 rad/s, the
axis turning 74° off the held one over one drop) took the batch smoother from 0.77° to 5.9° RMS and the stream's
filtered output to 15.9° (`benchmarks/stream_arrival.py 01 --kinds drop`). The densities are those of a hand or
limb: an angular-rate change of q_ω√τ ≈ 2 rad/s and a specific-force change of ≈ 7 m/s² in 0.5 s. A step of
normal length adds nothing, so a recording without gaps is unchanged bit for bit.
"""

from __future__ import annotations

import numpy as np

GAP_RATE_WALK = 3.0     # q_ω, rad/s^1.5
GAP_ACC_WALK = 10.0     # q_a, m/s^2.5
# a gap with more missing time than this starts a keyframe (factors.gyro.keyframe_layout; the stream closes its
# interval): the held rate's rotation is then uncertain by ≥ q_ω √(τ³/3) ≈ 1°. Shorter ones stay inside their
# interval with the variance (G1): a sample overtaken by its successor looks like a one-sample gap first and must
# still find its interval open.
KEYFRAME_GAP_S = 0.05
GAP_FACTOR = 1.5        # a step longer than 1.5 nominal steps holds missing time


def gap_steps(dt: np.ndarray, nominal_dt: float) -> np.ndarray:
    """(N,) bool: the steps that hold missing time, Δt > 1.5 T (the one rule for a gap; the stream's `gaps`
    counter, the layout's `gap_end` and (G1) all use it)."""
    return np.asarray(dt, float) > GAP_FACTOR * nominal_dt


def gap_variance(dt: np.ndarray, nominal_dt: float, q: float) -> np.ndarray:
    """Eq. (G1) per step: q² τ³ / 3 with τ = Δt − T on the steps longer than 1.5 T, 0 elsewhere.

    Args:
        dt: (N,) time steps, s; nominal_dt: T, the nominal step, s; q: walk density (q_ω or q_a).
    """
    dt = np.asarray(dt, float)
    tau = np.where(gap_steps(dt, nominal_dt), dt - nominal_dt, 0.0)
    return (q * q / 3.0) * tau**3


def keyframe_gap_step(nominal_dt: float) -> float:
    """The step beyond which a gap starts a keyframe: T + KEYFRAME_GAP_S (and at least 1.5 T)."""
    return max(GAP_FACTOR * nominal_dt, nominal_dt + KEYFRAME_GAP_S)


def has_gap(dt: np.ndarray, nominal_dt: float) -> bool:
    """Any step longer than 1.5 nominal steps (the stream's `gaps` counter uses the same rule)."""
    return bool(np.max(dt, initial=0.0) > GAP_FACTOR * nominal_dt)


def bias_segments(t_kf: np.ndarray, segment_s: float) -> np.ndarray:
    """Gyro-bias segment index (K−1,) of each keyframe interval from its start time t_kf (s from the session start):
    ⌊t_kf / segment_s⌋ (all 0 when segment_s ≤ 0), renumbered 0, 1, … without the segments no keyframe falls in (a
    declared gap longer than a segment: a bias with no factor, LM stalls, and no place in cpp_velocity's ordering)."""
    seg = np.floor(t_kf / segment_s).astype(int) if segment_s > 0 else np.zeros(len(t_kf), int)
    if len(seg) and seg[-1] + 1 != len(np.unique(seg)):
        seg = np.unique(seg, return_inverse=True)[1].astype(int)
    return seg
