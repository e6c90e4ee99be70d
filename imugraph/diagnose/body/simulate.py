"""Simulation of a body session from its fitted model (docs/diagnose_body.md §2).

The fitted model is the truth: the result's segment motion (`BodyResult.n_quat`, `n_pos`), the fitted
sensor-to-segment poses, and per sensor

    ỹ_g,i = s_ω_i + b̂_g(t_i) + e_g,i,   ỹ_a,i = nR_s,iᵀ (n_a_i − g_n) + b̂_a(t_i) + e_a,i,   e ~ N(0, σ²)    (BS1)

with s_ω, n_a from imugraph.sim.body.simulate_body (the segment motion first low-passed, zero-phase 4th-order
Butterworth at `LOWPASS_HZ`: the fitted orientations carry the integrated gyro noise, whose derivative times a
lever arm — σ_ω √2/dt · 0.4 m ≈ 0.1 m/s² at 60 Hz — would otherwise enter the simulated accelerometer as
noise the model does not have: measured, simulated acc residuals 10× the recording's on a simulated walk) ((P1)–(P3) there; readings by imugraph.sim.sensors'
(S1)–(S3)), b̂ the fitted bias path (piecewise constant, per keyframe) and σ the model's white noise (the
N-pose rest's, as the graph uses). Same time base and sensors as the recording; the magnetometer is the
simulator's ideal one (the base model uses it for the initial headings only).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.signal import butter, filtfilt

from imugraph.diagnose.body.fit import BodyFit, fit_body
from imugraph.geometry import quat_continuous, quat_normalize
from imugraph.io.body_session import BodySession

LOWPASS_HZ = 10.0


def smooth_motion(t: np.ndarray, n_quat: np.ndarray, n_pos: np.ndarray, cutoff_hz: float = LOWPASS_HZ):
    """Zero-phase low-pass of segment quaternions (sign-continuous, renormalised) and the root position;
    the other origins follow by the caller's forward kinematics."""
    dt = float(np.median(np.diff(t)))
    if cutoff_hz >= 0.5 / dt or t.size < 30:
        return n_quat, n_pos
    q = quat_continuous(n_quat)
    b, a = butter(4, cutoff_hz * 2 * dt)
    return quat_normalize(filtfilt(b, a, q, axis=0)), filtfilt(b, a, n_pos, axis=0)


def simulate_from_fit(bfit: BodyFit, rng: np.random.Generator, name_suffix: str = "+sim") -> BodySession:
    """A body session drawn from the fitted model (BS1), with the truth of `simulate_body`."""
    from imugraph.body.placement import Placement
    from imugraph.diagnose.effects.base import replace_session
    from imugraph.sim.body import BodyMotion, simulate_body
    from imugraph.sim.sensors import SensorParams

    s = bfit.session
    res = bfit.result
    skel = s.skeleton
    t = np.asarray(s.t, float)
    q, p = smooth_motion(t, np.asarray(res.n_quat, float), np.asarray(res.n_pos, float))
    motion = BodyMotion(t, tuple(skel.names), q, skel.forward_kinematics(q, p[:, 0]))
    placements = {n: Placement(bRs=sf.bRs, b_pos=sf.b_pos) for n, sf in bfit.sensors.items()}
    params = {n: SensorParams(gyro_noise=sf.sigma_gyr, acc_noise=sf.sigma_acc, g=bfit.g)
              for n, sf in bfit.sensors.items()}
    sim = simulate_body(motion, skel, placements, params, rng, name=s.name + name_suffix)
    sensors = {}
    for n, ses in sim.sensors.items():
        sf = bfit.sensors[n]
        sensors[n] = replace_session(ses, gyr=ses.gyr + sf.b_gyr, acc=ses.acc + sf.b_acc)
    return BodySession(sim.t, sensors, skel, sim.truth, s.source, sim.name, dict(s.meta, simulated_from_fit=True))


def fit_options(real: BodyFit, opts=None):
    """The body options the recording was fitted with (default BodyOptions), with the N-pose window the real
    fit found: simulations and refits are fitted exactly like the recording."""
    from dataclasses import replace

    from imugraph.graphs.body_model import BodyOptions

    opts = BodyOptions() if opts is None else opts
    if opts.npose is None and real.info.get("npose_window") is not None:
        opts = replace(opts, npose=tuple(real.info["npose_window"]))
    return opts


def fit_simulation(sim: BodySession, real: BodyFit, opts=None, warm: bool = True,
                   start: str = "solution") -> BodyFit:
    """Fit a simulation exactly like the recording (`fit_options`): the same graph and LM; warm: LM starts from
    the recording's solution turned into the simulation's own gauge (`warm_values`) instead of the
    gyro-integrated initial orientations (the simulation's truth IS that solution, low-passed), when both
    problems have the same keyframes; the gauge priors are the simulation's own, as in a cold fit.
    start (with warm): "solution" — `warm_values` as above; "generator" — `generator_values`: the same
    solution made consistent with the simulated readings (session 23: positions and velocities of the sensors
    the simulation integrated, joint centres and levers of its skeleton; the solution's own positions and levers
    disagree with them, so LM spent 16–18 iterations on the real walk removing a start cost of 1.7e7)."""
    from imugraph.diagnose.body.fit import _extract
    from imugraph.diagnose.body.lm import lm_optimize
    from imugraph.graphs.body import build_problem, full_graph

    opts = fit_options(real, opts)
    if not warm or real.problem is None or real.values is None:
        return fit_body(sim, opts, lm=real.info.get("lm"))
    t0 = time.perf_counter()
    pb = build_problem(sim, opts)
    same = np.array_equal(pb.kf, real.problem.kf)        # same keyframes: the recording's solution fits pb's keys
    x0 = pb.init
    if same:
        x0 = generator_values(sim, real, pb) if start == "generator" else warm_values(real, pb)
    x, info = lm_optimize(pb, full_graph(pb), x0, real.info.get("lm"))         # the recording's LM damping
    return _extract(sim, pb, x, dict(info, warm_start=same, start=start if same else "cold"), t0)


def warm_values(real: BodyFit, pb) -> "gtsam.Values":
    """The recording's solution in the gauge of problem pb: every pose, velocity and joint centre turned about
    the vertical by the heading difference of the root sensor at k = 0 (pb's initial value vs the solution:
    R_Δ = Rz(ψ_init − ψ_fit), the graph frame's only free rotation), levers and biases unchanged."""
    import gtsam

    from imugraph.factors import body as bf
    from imugraph.graphs.body_init import rz

    x = real.values
    k0 = bf.pose_key(0, 0)

    R_rel = pb.init.atPose3(k0).rotation().matrix() @ x.atPose3(k0).rotation().matrix().T
    psi = np.arctan2(R_rel[1, 0] - R_rel[0, 1], R_rel[0, 0] + R_rel[1, 1])      # yaw of R_rel (tilts agree)
    Rd = rz(psi)
    out = gtsam.Values()
    for key in x.keys():
        ch = chr(gtsam.Symbol(key).chr())
        if ch == "x":
            T = x.atPose3(key)
            out.insert(key, gtsam.Pose3(gtsam.Rot3(Rd @ T.rotation().matrix()), Rd @ np.asarray(T.translation())))
        elif ch in ("v", "j"):
            v = Rd @ np.asarray(x.atVector(key) if ch == "v" else x.atPoint3(key), float)
            out.insert(key, v)
        elif ch == "l":
            out.insert(key, np.asarray(x.atPoint3(key), float))
        elif ch == "b":
            out.insert(key, x.atConstantBias(key))
    return out


def generator_values(sim: BodySession, real: BodyFit, pb) -> "gtsam.Values":
    """`warm_values` with every state the simulation generated replaced by its generating value (simulate_body's
    truth: the fitted model it was drawn from, in the same gauge turn R_Δ and shifted so that the root sensor's
    position at k = 0 is the warm value's): sensor poses nR_s, p_s and velocities v_s at the keyframes, joint
    centres J_j = the child segment's origin (BodyJoint: "centre at the child's origin"), levers
    l = nR_s(t_0)ᵀ (J_j(t_0) − p_s(t_0)) (rigid: the same at every t); biases the solution's (= the generator's
    piecewise-constant ones). Only the start of LM changes, not the graph; it is the information `warm_values`
    already uses (the recording's solution), made consistent with what the simulation integrated."""
    import gtsam

    from imugraph.factors import body as bf
    from imugraph.geometry import quat_to_rotmat

    from imugraph.graphs.body_init import rz

    x0 = warm_values(real, pb)
    tr = sim.truth
    k0 = bf.pose_key(0, 0)
    R_rel = pb.init.atPose3(k0).rotation().matrix() @ real.values.atPose3(k0).rotation().matrix().T
    Rd = rz(np.arctan2(R_rel[1, 0] - R_rel[0, 1], R_rel[0, 0] + R_rel[1, 1]))      # warm_values' R_Δ
    d = np.asarray(x0.atPose3(k0).translation(), float) - Rd @ np.asarray(tr["sensor_pos"][pb.names[0]][pb.kf[0]])
    nR = {n: quat_to_rotmat(np.asarray(sim.sensors[n].quat, float)[pb.kf]) for n in pb.names}
    new = {}
    for s, n in enumerate(pb.names):
        p, v = np.asarray(tr["sensor_pos"][n])[pb.kf], np.asarray(tr["sensor_vel"][n])[pb.kf]
        for k in range(pb.K):
            new[bf.pose_key(s, k)] = gtsam.Pose3(gtsam.Rot3(Rd @ nR[n][k]), Rd @ p[k] + d)
            new[bf.vel_key(s, k)] = Rd @ v[k]
    names = list(tr["names"])
    J = {j: np.asarray(tr["n_pos"])[pb.kf, names.index(jt.child)] for j, jt in enumerate(pb.joints)}
    for j in J:
        for k in range(pb.K):
            new[bf.joint_key(j, k)] = Rd @ J[j][k] + d
    for i, (seg, j, _) in enumerate(pb.levers):
        new[bf.lever_key(i)] = nR[seg][0].T @ (J[j][0] - np.asarray(tr["sensor_pos"][seg])[pb.kf[0]])
    out = gtsam.Values()
    for key in x0.keys():                       # the types warm_values inserts (Pose3, vectors, biases)
        if key in new:
            out.insert(key, new[key])
        elif chr(gtsam.Symbol(key).chr()) == "b":
            out.insert(key, x0.atConstantBias(key))
        elif chr(gtsam.Symbol(key).chr()) == "x":
            out.insert(key, x0.atPose3(key))
        else:
            out.insert(key, np.asarray(x0.atVector(key) if chr(gtsam.Symbol(key).chr()) == "v" else x0.atPoint3(key)))
    return out
