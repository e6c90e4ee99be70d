"""BVH-driven body simulator: segment trajectories → virtual IMUs on the segments → readings.

Pipeline:
1. `motion_from_bvh`: segment orientations from a BVH file (imugraph.body.bvh_map, eq. M1), a static
   N-pose prefix (all segments aligned with the subject's initial heading: the pose a calibration
   asks for), blended into the first frame with a quintic smoothstep, then resampled to `rate_hz`.
   Segment origins are recomputed by the skeleton's forward kinematics (K1), so the truth satisfies
   the joint constraints exactly (folded BVH joints' own rotations are dropped). Before that, mocap
   glitches are repaired: joint rotations faster than 25 rad/s (CMU 131_01's right wrist turns 60° in one
   1/120 s frame, > 100 rad/s), which no body segment or gyroscope does, are replaced by the geodesic
   across the bad frames (imugraph.body.repair, G1–G2; the report is in BodyMotion.info["repair"]); then
   the segment quaternions (made sign-continuous) and the root position are low-pass filtered (zero-phase
   4th-order Butterworth, default 10 Hz, then renormalised).
2. `random_placements`: a plausible pose of each sensor on its segment (imugraph.body.placement: on the
   skin, mid-segment, the sensor's z axis along the outward surface normal) plus a random rotation and shift.
3. `simulate_body`: per sensed segment, sensor orientation and position

       nRs = nRb · bRs,     n_p_s = n_p_b + nRb · b_pos                                        (P1)

   Angular rate: the rate constant over [t_k, t_{k+1}) that carries nRs,k to nRs,k+1 exactly,

       s_ω_k = Log(nRs,kᵀ · nRs,k+1) / Δt_k                                                     (P2)

   (the discretisation of `imugraph.sim.motion`, eq. 1: strapdown integration reproduces nRs).
   Linear acceleration: the mean over the same interval, from a smooth motion — the orientations are
   interpolated by natural cubic splines of the quaternion components (renormalised) and the root
   position by a cubic spline; n_p_s(t) follows by (K1)+(P1); its velocity v(t) by a central
   difference with h = 10⁻⁴ s on that smooth curve, and

       n_acc_k = (v(t_k+1) − v(t_k)) / Δt_k                                                     (P3)

   so v_{k+1} = v_k + n_acc_k Δt_k holds exactly (the discrete IMU model of preintegration, with the
   specific force taken in the sensor frame at t_k). Readings then come from
   `imugraph.sim.sensors.simulate_imu` (S1)–(S3) with each sensor's own parameters and noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import butter, filtfilt

from imugraph.body.bvh_map import segment_motion
from imugraph.body.placement import Placement, nominal_placement  # noqa: F401  (re-exported)
from imugraph.body.repair import MAX_JOINT_RATE, repair_glitches
from imugraph.body.skeleton import Skeleton, fill_unsensed
from imugraph.errors import SessionError
from imugraph.geometry import (expmap, quat_conj, quat_continuous, quat_mul, quat_normalize, quat_slerp,
                               quat_to_rotmat, quat_to_rotvec, rotmat_to_quat)
from imugraph.io.body_session import BodySession
from imugraph.sim.sensors import SensorParams, simulate_imu

_SRC = "<imugraph.sim.body>"


@dataclass(frozen=True)
class BodyMotion:
    """Segment trajectories: t (T,) s; names (S,); n_quat (T, S, 4) segment → n; n_pos (T, S, 3) origins, m;
    info: how they were made (`motion_from_bvh`: {"repair": the glitch-repair report, ...})."""

    t: np.ndarray
    names: tuple
    n_quat: np.ndarray
    n_pos: np.ndarray
    info: dict = field(default_factory=dict)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    """Quintic 6u⁵ − 15u⁴ + 10u³: 0 → 1 with zero first and second derivatives at both ends."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2)


def _heading(q: np.ndarray) -> np.ndarray:
    """(4,) rotation about z by the yaw of q's x axis (the subject's facing direction)."""
    x = quat_to_rotmat(q)[:, 0]
    return rotmat_to_quat(expmap(np.array([0.0, 0.0, np.arctan2(x[1], x[0])])))


class _Smooth:
    """Cubic-spline motion (module docstring, P3): segment rotations and root position at any t."""

    def __init__(self, t: np.ndarray, n_quat: np.ndarray, n_root: np.ndarray):
        self.q = CubicSpline(t, quat_continuous(n_quat), axis=0, bc_type="natural")
        self.p = CubicSpline(t, n_root, axis=0, bc_type="natural")

    def quat(self, t: np.ndarray) -> np.ndarray:
        return quat_normalize(self.q(t))

    def root(self, t: np.ndarray) -> np.ndarray:
        return self.p(t)


def motion_from_bvh(path: Union[str, Path], rate_hz: float = 60.0, npose_s: float = 2.0, blend_s: float = 1.0,
                    *, mapping: Optional[dict] = None, units_m: Optional[float] = None,
                    skip_s: Optional[float] = None,
                    duration_s: Optional[float] = None, tie_unsensed: bool = False,
                    lowpass_hz: Optional[float] = 10.0,
                    max_joint_rate: Optional[float] = MAX_JOINT_RATE) -> tuple[Skeleton, BodyMotion]:
    """Segment motion of a BVH file with an N-pose prefix, resampled (module docstring, step 1).

    Args:
        path: the BVH file (CMU or Xsens MVN skeleton, or one written by imugraph).
        rate_hz: output rate, Hz.
        npose_s: length of the static N-pose at the start, s (0: none).
        blend_s: length of the smooth transition N-pose → first used BVH frame, s.
        mapping: MVN segment → BVH joint (None: built-in, see bvh_map).
        units_m: metres per BVH unit (None: detected).
        skip_s: BVH time to drop at the start, s. None: drop frame 0 only when the root jumps by more
            than 5 cm from frame 0 to frame 1 (the Xsens MVN export's frame 0 is a T-pose reference
            placed at the origin).
        duration_s: BVH time to use after skip_s (None: to the end).
        tie_unsensed: replace the unsensed segments' rotations by the ties (K2) of the sensed ones, so
            the truth follows the estimator's model exactly.
        lowpass_hz: cut-off of the zero-phase low-pass on the BVH motion, Hz (None: no filter).
        max_joint_rate: joint rotations faster than this (rad/s) are glitches, repaired before the
            low-pass (imugraph.body.repair, eqs. G1–G2); None: no repair.
    Returns:
        (Skeleton, BodyMotion) with t from 0 at `rate_hz`; BodyMotion.info["repair"] = the repair report
        (frames replaced per segment, runs left unrepaired, max joint rates before and after).
    Raises:
        SessionError: unreadable BVH, or fewer than 4 frames left after skip/duration.
    """
    skel, _, t_b, q_b, p_b = segment_motion(path, mapping, units_m)
    if skip_s is None:
        jump = t_b.size > 1 and np.linalg.norm(p_b[1, 0] - p_b[0, 0]) > 0.05
        skip_s = 0.5 * (t_b[1] - t_b[0]) if jump else 0.0
    keep = (t_b >= skip_s - 1e-9) & (t_b <= (np.inf if duration_s is None else skip_s + duration_s) + 1e-9)
    if keep.sum() < 4:
        raise SessionError(str(path), "Frames", f"{int(keep.sum())} frames after skip/duration", "at least 4")
    t_b, q_b, root = t_b[keep] - t_b[keep][0], q_b[keep], p_b[keep, 0]
    repair = {}
    if max_joint_rate is not None:
        q_b, repair = repair_glitches(skel.parents, skel.names, t_b, q_b, max_joint_rate)
    if tie_unsensed:
        q_b = fill_unsensed(skel, {n: q_b[:, skel.index(n)] for n in skel.sensed})
    dt = float(np.median(np.diff(t_b)))
    if lowpass_hz is not None and lowpass_hz < 0.5 / dt and t_b.size > 30:
        b, a = butter(4, lowpass_hz * 2 * dt)
        q_b = quat_normalize(filtfilt(b, a, quat_continuous(q_b), axis=0))
        root = filtfilt(b, a, root, axis=0)
    n_pre = int(round((npose_s + blend_s) / dt))
    if n_pre > 0:
        t_pre = np.arange(n_pre) * dt
        u = _smoothstep((t_pre - npose_s) / max(blend_s, 1e-9))
        q_n = np.broadcast_to(_heading(q_b[0, 0]), q_b[0].shape)
        q_pre = np.stack([quat_slerp(q_n, q_b[0], np.full(len(skel.names), uk)) for uk in u])
        p_pre = root[0] + 0.0 * u[:, None]
        t_b = np.concatenate([t_pre, t_b + n_pre * dt])
        q_b = np.concatenate([q_pre, q_b])
        root = np.concatenate([p_pre, root])
    smooth = _Smooth(t_b, q_b, root)
    t = np.arange(0.0, t_b[-1] + 1e-9, 1.0 / rate_hz)
    n_quat = smooth.quat(t)
    n_pos = skel.forward_kinematics(n_quat, smooth.root(t))
    info = {"source": str(path), "repair": repair, "lowpass_hz": lowpass_hz}
    return skel, BodyMotion(t=t, names=skel.names, n_quat=n_quat, n_pos=n_pos, info=info)


def random_placements(skel: Skeleton, rng: np.random.Generator, max_angle_deg: float = 30.0,
                      max_shift_m: float = 0.03, names: Optional[list] = None) -> dict:
    """A random plausible placement per sensed segment (`nominal_placement` perturbed).

    The rotation is the nominal one times Exp(θ a) with a uniform random axis a and θ ~ U[0, max_angle];
    the position is shifted along the segment's long axis and sideways on the skin by U[−max_shift, max_shift].

    Returns:
        {segment name: Placement}.
    """
    out = {}
    for name in (skel.sensed if names is None else names):
        nom = nominal_placement(skel, name)
        a = rng.standard_normal(3)
        theta = np.deg2rad(rng.uniform(0.0, max_angle_deg))
        bRs = nom.bRs @ expmap(theta * a / np.linalg.norm(a))
        shift = nom.bRs[:, :2] @ rng.uniform(-max_shift_m, max_shift_m, 2)   # within the skin's tangent plane
        out[name] = Placement(bRs=bRs, b_pos=nom.b_pos + shift)
    return out


def sensor_trajectory(motion: BodyMotion, skel: Skeleton, name: str, placement: Placement,
                      h: float = 1e-4) -> tuple[np.ndarray, ...]:
    """Sensor orientation (T, 4), position (T, 3), rate s_ω (T, 3), n_acc (T, 3), velocity (T, 3): (P1)–(P3)."""
    i = skel.index(name)
    t = motion.t
    q_s = quat_mul(motion.n_quat[:, i], rotmat_to_quat(placement.bRs))                     # (P1)
    p_s = motion.n_pos[:, i] + np.einsum("tab,b->ta", quat_to_rotmat(motion.n_quat[:, i]), placement.b_pos)
    dt = np.diff(t)
    w = quat_to_rotvec(quat_mul(quat_conj(q_s[:-1]), q_s[1:])) / dt[:, None]               # (P2)
    s_omega = np.vstack([w, w[-1:]])
    smooth = _Smooth(t, motion.n_quat, motion.n_pos[:, 0])

    def position(tt: np.ndarray) -> np.ndarray:
        q = smooth.quat(tt)
        pos = skel.forward_kinematics(q, smooth.root(tt))[:, i]
        return pos + np.einsum("tab,b->ta", quat_to_rotmat(q[:, i]), placement.b_pos)

    v = (position(t + h) - position(t - h)) / (2 * h)
    a = np.diff(v, axis=0) / dt[:, None]                                                     # (P3)
    n_acc = np.vstack([a, a[-1:]])
    return q_s, p_s, s_omega, n_acc, v


def simulate_body(motion: BodyMotion, skel: Skeleton, placements: dict,
                  params: Union[SensorParams, dict], rng: np.random.Generator, *, name: str = "sim_body") -> BodySession:
    """Readings of one IMU per placed segment (module docstring, step 3).

    Args:
        motion: segment trajectories (names in `skel` order).
        skel: the skeleton (forward kinematics for the smooth positions).
        placements: {segment: Placement} (the segments to equip).
        params: one SensorParams for all sensors, or {segment: SensorParams}.
        rng: random generator (noise is drawn sensor by sensor in `placements` order).
        name: session name.
    Returns:
        BodySession with per-sensor Sessions (quat = the sensor's true nRs) and truth {"n_quat", "n_pos",
        "names", "placements": {segment: {"bRs", "b_pos"}}, "sensor_pos" and "sensor_vel": {segment: (T, 3)}}.
    Raises:
        SessionError: motion and skeleton disagree, missing parameters for a sensor.
    """
    if tuple(motion.names) != tuple(skel.names) or motion.n_quat.shape != (motion.t.size, len(skel.names), 4):
        raise SessionError(_SRC, "motion", f"names {motion.names[:3]}…, n_quat {motion.n_quat.shape}",
                           f"the skeleton's {len(skel.names)} segments in order")
    sensors, truth_place, sensor_pos, sensor_vel = {}, {}, {}, {}
    for seg, pl in placements.items():
        p = params.get(seg) if isinstance(params, dict) else params
        if p is None:
            raise SessionError(_SRC, "params", f"no SensorParams for {seg}", "one per placed segment")
        q_s, p_s, s_omega, n_acc, v_s = sensor_trajectory(motion, skel, seg, pl)
        ses = simulate_imu(motion.t, q_s, s_omega, n_acc, p, rng, name=seg)
        sensors[seg] = ses
        truth_place[seg] = pl.to_dict()
        sensor_pos[seg], sensor_vel[seg] = p_s, v_s
    truth = {"n_quat": motion.n_quat, "n_pos": motion.n_pos, "names": list(skel.names),
             "placements": truth_place, "sensor_pos": sensor_pos, "sensor_vel": sensor_vel}
    return BodySession(t=motion.t.copy(), sensors=sensors, skeleton=skel, truth=truth, source="<simulation>",
                       name=name, meta={"simulated": True})
