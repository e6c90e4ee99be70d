"""Random rigid-body motions for simulating one IMU: smooth rotations about all axes, with rests.

Discretisation (the contract every test and solver relies on): samples are at t_k = k / rate_hz; the
body angular rate ω_k is constant over [t_k, t_{k+1}), so the orientation follows exactly

    q_{k+1} = q_k ⊗ Exp(ω_k Δt),   Exp(θ) = [cos(|θ|/2), sin(|θ|/2) θ/|θ|]          (1)

(the noise-free form of Kok & Schön's gyroscope-driven dynamic model). A gyroscope that
reads b_omega without noise and bias therefore reproduces nRb to round-off when integrated with (1),
e.g. `imugraph.geometry.integrate_gyro(b_omega, dt, nRb[0])`.

The angular rate is band-limited Gaussian noise in the body frame (a random walk on SO(3), which
covers the sphere of directions well), softly limited to `max_rate`, and multiplied by an envelope
that is exactly zero during the rest periods (start, end and optional pauses) with smooth ramps, so
that rest detectors see ω = 0 and a constant orientation there.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import quat_mul, quat_normalize, rotvec_to_quat

_SOURCE = "simulated motion"


class Motion(NamedTuple):
    """A simulated motion (unpacks as `t, nRb, b_omega, n_acc`).

    Attributes:
        t: (N,) sample times in s, t_k = k / rate.
        nRb: (N, 4) orientation body → nav, quaternions w, x, y, z (w ≥ 0).
        b_omega: (N, 3) true angular rate in the body frame, rad/s, constant over [t_k, t_{k+1}).
        n_acc: (N, 3) linear acceleration of the sensor in the nav frame, m/s² (gravity excluded).
    """

    t: np.ndarray
    nRb: np.ndarray
    b_omega: np.ndarray
    n_acc: np.ndarray


def random_rotation_motion(
    duration_s: float,
    rate_hz: float,
    rng: np.random.Generator,
    *,
    rest_s: float = 2.0,
    max_rate: float = 4.0,
    rms_rate: float = 1.2,
    bandwidth_hz: float = 0.4,
    pauses: int = 0,
    pause_s: float = 1.5,
    ramp_s: float = 0.5,
    translation_m: float = 0.0,
    q0: Optional[np.ndarray] = None,
) -> Motion:
    """Smooth random rotations about all three axes, at rest at the start and the end.

    Args:
        duration_s: length of the motion in s (N = round(duration_s · rate_hz) samples).
        rate_hz: sampling rate in Hz.
        rng: random generator (the only source of randomness: same seed → same motion).
        rest_s: rest at the start and at the end, s (ω = 0 and n_acc = 0 exactly).
        max_rate: soft upper bound of |ω|, rad/s (|ω| < max_rate everywhere).
        rms_rate: RMS per body axis of the angular rate before the soft limit, rad/s.
        bandwidth_hz: width (1σ) of the Gaussian spectrum of the angular rate, Hz.
        pauses: number of extra rests, evenly spaced inside the motion.
        pause_s: length of each extra rest, s.
        ramp_s: length of the smooth (quintic) ramps in and out of every rest, s.
        translation_m: RMS displacement of an optional smooth random translation, m (0: none).
        q0: (4,) initial orientation nRb w, x, y, z; None draws a uniformly random one.

    Returns:
        Motion (t (N,), nRb (N, 4), b_omega (N, 3) rad/s, n_acc (N, 3) m/s²).

    Raises:
        SessionError: non-positive duration or rate, or rests longer than the motion.
    """
    n = _check_timing(duration_s, rate_hz, rest_s, pauses, pause_s)
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt
    rests = _rest_intervals(t[-1], rest_s, pauses, pause_s)
    env = _rest_envelope(t, rests, ramp_s)

    b_omega = rms_rate * _bandlimited(n, rate_hz, bandwidth_hz, rng)
    b_omega = _soft_limit(b_omega, max_rate) * env[:, None]

    q_start = _random_quat(rng) if q0 is None else quat_normalize(np.asarray(q0, float))
    nRb = _integrate_exact(b_omega, dt, q_start)

    n_acc = np.zeros((n, 3))
    if translation_m > 0.0:
        # Rests widened by 1.5 samples: the central difference then stays exactly 0 inside them.
        env_pos = _rest_envelope(t, rests + np.array([-1.5 * dt, 1.5 * dt]), ramp_s)
        n_acc = _translation_acc(n, rate_hz, env_pos, translation_m, rng)
    return Motion(t, nRb, b_omega, n_acc)


def _check_timing(duration_s: float, rate_hz: float, rest_s: float, pauses: int, pause_s: float) -> int:
    """Validate the timing arguments and return the number of samples N."""
    if not (rate_hz > 0 and duration_s > 0):
        raise SessionError(_SOURCE, "duration", f"{duration_s:g} s at {rate_hz:g} Hz",
                           "a positive duration (s) and rate (Hz)")
    n = int(round(duration_s * rate_hz))
    resting = 2 * rest_s + pauses * pause_s
    if n < 3 or resting >= duration_s:
        rests = f"rest_s = {rest_s:g} s at each end"
        if pauses:
            rests += f", {pauses} pauses of pause_s = {pause_s:g} s"
        raise SessionError(_SOURCE, "duration", f"{duration_s:g} s ({n} samples at {rate_hz:g} Hz), of which the "
                           f"rests take {resting:g} s ({rests})",
                           f"a duration longer than the {resting:g} s of rests, with at least 3 samples")
    return n


def _rest_intervals(t_end: float, rest_s: float, pauses: int, pause_s: float) -> np.ndarray:
    """(M, 2) [start, stop] of every rest in s: start, evenly spaced pauses, end."""
    centres = np.linspace(rest_s, t_end - rest_s, pauses + 2)[1:-1]
    inner = np.stack([centres - pause_s / 2, centres + pause_s / 2], -1)
    return np.vstack([[[-np.inf, rest_s]], inner, [[t_end - rest_s, np.inf]]])


def _rest_envelope(t: np.ndarray, rests: np.ndarray, ramp_s: float) -> np.ndarray:
    """(N,) envelope: 0 inside rests, 1 far from them, quintic smoothstep over `ramp_s` between."""
    dist = np.maximum(np.maximum(rests[None, :, 0] - t[:, None], t[:, None] - rests[None, :, 1]), 0.0)
    u = np.clip(dist.min(axis=1) / max(ramp_s, 1e-12), 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)


def _bandlimited(n: int, rate_hz: float, bandwidth_hz: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) smooth Gaussian noise, unit RMS per axis, Gaussian spectrum of width `bandwidth_hz`."""
    white = rng.standard_normal((n, 3))
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    gain = np.exp(-0.5 * (f / bandwidth_hz) ** 2)
    x = np.fft.irfft(np.fft.rfft(white, axis=0) * gain[:, None], n=n, axis=0)
    x -= x.mean(axis=0)
    return x / np.sqrt(np.mean(x**2, axis=0))


def _soft_limit(w: np.ndarray, max_norm: float) -> np.ndarray:
    """Scale each row so that |w| → max_norm·tanh(|w|/max_norm) (smooth, < max_norm)."""
    norm = np.linalg.norm(w, axis=1, keepdims=True)
    safe = np.where(norm > 0, norm, 1.0)
    return np.where(norm > 0, w * (max_norm * np.tanh(norm / max_norm) / safe), 0.0)


def _random_quat(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random unit quaternion (normalised 4-D Gaussian), w ≥ 0."""
    return quat_normalize(rng.standard_normal(4))


def _integrate_exact(b_omega: np.ndarray, dt: float, q_start: np.ndarray) -> np.ndarray:
    """Eq. (1) for all k at once: q_k = q_0 ⊗ Exp(ω_0 Δt) ⊗ … ⊗ Exp(ω_{k−1} Δt), (N, 4).

    The prefix products are computed by a parallel (Hillis–Steele) scan: ⌈log2 N⌉ vectorised
    Hamilton products instead of N sequential ones; quaternion products are associative, so the
    result equals the sequential recursion up to round-off (≈ 1e-15 per level).
    """
    prefix = rotvec_to_quat(b_omega[:-1] * dt)          # Exp(ω_k Δt), k = 0 … N−2
    step = 1
    while step < prefix.shape[0]:
        prefix[step:] = quat_mul(prefix[:-step], prefix[step:])
        step *= 2
    q = np.vstack([q_start[None, :], quat_mul(q_start[None, :], prefix)])
    return quat_normalize(q)


def _translation_acc(n: int, rate_hz: float, env: np.ndarray, rms_m: float,
                     rng: np.random.Generator) -> np.ndarray:
    """(n, 3) nav-frame acceleration of a smooth random translation p = rms_m · env · x(t), m/s².

    a_k = (p_{k+1} − 2 p_k + p_{k−1}) / Δt², zero at both ends; exactly zero inside the rests when
    `env` vanishes one sample beyond them.
    """
    n_pos = rms_m * env[:, None] * _bandlimited(n, rate_hz, 0.5, rng)
    n_acc = np.zeros_like(n_pos)
    n_acc[1:-1] = (n_pos[2:] - 2.0 * n_pos[1:-1] + n_pos[:-2]) * rate_hz**2
    return n_acc
