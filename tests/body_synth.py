"""Tiny synthetic multi-IMU body sessions for the body-estimator tests (independent of imugraph.sim.body).

A short MVN-named chain (Pelvis → Right/Left UpperLeg → Right LowerLeg, optionally an unsensed L5 between
the Pelvis and a sensed T8) with analytic motion: a static N-pose, then smooth sinusoidal joint rotations
and root motion blended in. Truth is computed here, not by the code under test:

    nRb_child(t) = nRb_parent(t) · Exp(θ_j(t))             joint rotation (neutral: identity)
    p_child(t)   = p_parent(t) + nRb_parent(t) · offset      segment origins (forward kinematics)
    nRs(t) = nRb(t) · bRs,   n_p_s(t) = p(t) + nRb(t) · b_pos  sensor pose on its segment

The sensors sit near the estimator's assumed site (imugraph.body.placement.nominal_placement, its prior):
bRs = bRs_nom · Exp(random ≤ max_place_deg), b_pos = b_pos_nom shifted ≤ 3 cm on the skin.

Gyro sample k = Log(R(t_k)ᵀ R(t_{k+1}))/dt (the rate constant over [t_k, t_{k+1}), as the preintegration
assumes); n_acc = second derivative of the sensor position at the interval midpoint (central difference).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imugraph.body.placement import nominal_placement
from imugraph.geometry import expmap, logmap, rotmat_to_quat
from imugraph.sim.sensors import SensorParams, simulate_imu


@dataclass(frozen=True)
class MiniSkeleton:
    """Duck-typed stand-in for imugraph.body.skeleton.Skeleton (the fields the estimator reads)."""
    names: tuple
    parents: tuple
    offsets: np.ndarray
    sensed: tuple
    ends: np.ndarray

    def index(self, name: str) -> int:
        return self.names.index(name)

    def children(self, name: str) -> list:
        i = self.index(name)
        return [n for n, p in zip(self.names, self.parents) if p == i]

    def neutral_positions(self) -> np.ndarray:
        """Segment origins in the neutral pose, root at the origin (as Skeleton's; BodyOptions.init "auto" reads it)."""
        pos = np.zeros((len(self.names), 3))
        for i in range(1, len(self.names)):
            pos[i] = pos[self.parents[i]] + np.asarray(self.offsets[i], float)
        return pos


@dataclass(frozen=True)
class MiniBodySession:
    t: np.ndarray
    sensors: dict
    skeleton: MiniSkeleton
    truth: dict | None = None
    source: str = "<synthetic>"
    name: str = "chain"
    meta: dict = field(default_factory=dict)


def chain_skeleton(with_spine: bool = False) -> MiniSkeleton:
    names = ["Pelvis", "RightUpperLeg", "RightLowerLeg", "LeftUpperLeg"]
    parents = [-1, 0, 1, 0]
    offsets = [[0, 0, 0], [0, -0.09, -0.06], [0, 0, -0.44], [0, 0.09, -0.06]]
    ends = [[0, 0, 0.1], [0, 0, -0.44], [0, 0, -0.42], [0, 0, -0.44]]
    sensed = list(names)
    if with_spine:
        names += ["L5", "T8"]
        parents += [0, 4]
        offsets += [[0, 0, 0.1], [0, 0, 0.25]]
        ends += [[0, 0, 0.25], [0, 0, 0.2]]
        sensed += ["T8"]
    return MiniSkeleton(tuple(names), tuple(parents), np.array(offsets, float), tuple(sensed),
                        np.array(ends, float))


def _angles(t: np.ndarray, S: int, env: np.ndarray, rng: np.random.Generator, amp_deg: float):
    """(T, S, 3) joint rotation vectors: sums of sinusoids, 0 during the N-pose (env = 0)."""
    out = np.zeros((t.size, S, 3))
    for s in range(S):
        for a in range(3):
            f = rng.uniform(0.25, 1.0, 2)
            ph = rng.uniform(0, 2 * np.pi, 2)
            amp = np.deg2rad(amp_deg) * (1.0 if a == 1 else 0.5)
            out[:, s, a] = amp * env * (0.7 * np.sin(2 * np.pi * f[0] * t + ph[0]) + 0.3 * np.sin(2 * np.pi * f[1] * t + ph[1])
                                        - 0.7 * np.sin(ph[0]) - 0.3 * np.sin(ph[1]))
    return out


def _poses(t, skel, env, seed, amp_deg, hinge_knee=False, root_move=True):
    """Segment rotations (T, S, 3, 3) and origins (T, S, 3) at times t (deterministic in seed)."""
    rng = np.random.default_rng(seed)
    S = len(skel.names)
    th = _angles(t, S, env, rng, amp_deg)
    if hinge_knee:                                   # the knee turns about its lateral y axis only
        th[:, skel.index("RightLowerLeg"), [0, 2]] = 0.0
    f = rng.uniform(0.2, 0.5, 3)
    env = env if root_move else 0.0 * env
    root_p = np.stack([0.4 * env * np.sin(2 * np.pi * f[0] * t), 0.3 * env * np.sin(2 * np.pi * f[1] * t),
                       0.9 + 0.05 * env * np.sin(2 * np.pi * f[2] * t)], -1)
    R = np.zeros((t.size, S, 3, 3))
    p = np.zeros((t.size, S, 3))
    for i, par in enumerate(skel.parents):
        if par < 0:
            R[:, i] = expmap(th[:, i] * np.array([0.4, 0.4, 1.5]))   # root: mostly heading changes
            p[:, i] = root_p
        else:
            R[:, i] = R[:, par] @ expmap(th[:, i])
            p[:, i] = p[:, par] + np.einsum("tij,j->ti", R[:, par], skel.offsets[i])
    return R, p


def _envelope(t: np.ndarray, npose_s: float, blend_s: float = 1.0) -> np.ndarray:
    u = np.clip((t - npose_s) / blend_s, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def chain_session(duration_s: float = 12.0, rate_hz: float = 60.0, seed: int = 0, noisy: bool = True,
                  max_place_deg: float = 30.0, with_spine: bool = False, npose_s: float = 2.0,
                  amp_deg: float = 35.0, hinge_knee: bool = False, mag: bool = False,
                  root_move: bool = True) -> MiniBodySession:
    """A synthetic multi-IMU session with truth (segment quats, origins, placements)."""
    skel = chain_skeleton(with_spine)
    rng = np.random.default_rng(seed + 1000)
    dt = 1.0 / rate_hz
    t = np.arange(int(round(duration_s * rate_hz))) * dt
    def poses(tt):
        return _poses(tt, skel, _envelope(tt, npose_s), seed, amp_deg, hinge_knee, root_move)

    R, p = poses(t)
    R1, _ = poses(t + dt)
    h = 1e-3
    tm = t + dt / 2
    Rc, pm = poses(tm)
    Rp, pp = poses(tm + h)
    Rm, pn = poses(tm - h)
    sensors, placements = {}, {}
    for name in skel.sensed:
        i = skel.index(name)
        ax = rng.standard_normal(3)
        nom = nominal_placement(skel, name)
        bRs = nom.bRs @ expmap(ax / np.linalg.norm(ax) * np.deg2rad(rng.uniform(0.5, 1.0) * max_place_deg))
        b_pos = nom.b_pos + nom.bRs[:, :2] @ rng.uniform(-0.03, 0.03, 2)          # shifted on the skin
        nRs = R[:, i] @ bRs
        w = logmap(np.swapaxes(nRs, 1, 2) @ (R1[:, i] @ bRs)) / dt
        pos = lambda RR, PP: PP[:, i] + np.einsum("tij,j->ti", RR[:, i], b_pos)   # noqa: E731
        n_acc = (pos(Rp, pp) - 2 * pos(Rc, pm) + pos(Rm, pn)) / h**2
        if noisy:
            prm = SensorParams(gyro_bias=rng.normal(0, 0.01, 3), gyro_noise=0.004, acc_noise=0.04,
                               acc_bias=rng.normal(0, 0.05, 3), mag_noise=0.01 if mag else 0.0)
        else:
            prm = SensorParams()
        ses = simulate_imu(t, rotmat_to_quat(nRs), w, n_acc, prm, rng, name=name)
        sensors[name] = ses if mag else ses.with_mag(np.full_like(ses.mag, np.nan))
        placements[name] = {"bRs": bRs, "b_pos": b_pos}
    truth = {"n_quat": rotmat_to_quat(R), "n_pos": p, "names": list(skel.names), "placements": placements}
    return MiniBodySession(t=t, sensors=sensors, skeleton=skel, truth=truth)
