"""Multi-IMU body motion capture as one factor graph (Kok, Hol & Schön, IFAC 2014), batch solver.

Graph (factors (B1)–(B5) in imugraph.factors.body): per sensed segment s and keyframe k the sensor pose
X(s,k) = nTs and velocity V(s,k); per sensor one IMU bias B(s,m) per bias segment m (`bias_segment_s`, 1 s)
joined by a random walk b_{m+1} − b_m ~ N(0, rw² Δt) (BetweenFactorConstantBias; `BodyOptions.bias_rw`); per joint j (between sensed segments, see
imugraph.graphs.body_model) and keyframe k the joint centre J(j,k); per (sensor, joint) one lever arm l,
constant in time, with a prior around the nominal placement (the sensor-to-segment position factor).

    minimise  Σ_s,k ‖IMU(B1)‖² + Σ_j,k ‖J − nTs_P l_P‖² + ‖J − nTs_C l_C‖²  (hard: constrained, B2)
              + Σ ‖l − l_nom‖²/σ_l² (B3) + bias priors + gauge + [hinges (B4)] + [magnetometers (B5)]

Gauge: the root sensor's position (0) and heading at k = 0 (σ 1e-3 rad); every other sensor a weak heading
prior (σ 1 rad) at k = 0 from the N-pose assumption; without magnetometers the relative headings are then
made observable by the joints as the subject moves (tests/test_body_graph.py starts the non-root sensors
20–30° off in heading and checks they are recovered).

Sensor-to-segment rotation bRs: from the static N-pose (segments world-aligned, facing the body's forward
heading ψ = heading of (J_leftHip − J_rightHip) × z): bRs = Rz(ψ)ᵀ nRs(N-pose), see body_output.

Solver: with C++ factors only, gtsam's LevenbergMarquardtOptimizer (COLAMD). With hinge CustomFactors a
Python-driven LM (GTSAM_NOTES: the C++ optimizers copy the Values into every Python callback, O(N²)); hinges
need bRs, so they are added in a second pass after a first solve without them.

Choices, measured on imugraph.sim.body sessions (17 IMUs, random placements ≤ 30°, MEMS noise and bias;
"worst" = largest RMS error of a parent→child relative rotation, relpos = segment origins vs the pelvis;
these comparisons ran with gyro_bias_sigma 0.02, before it became 0.002, see `BodyOptions`):
- Joints stiff-soft, σ = 3 mm, not hard: with noiseModel.Constrained gtsam's LM made 0 iterations on a
  4-sensor chain (every trial step costs inf: the nonlinear constraint never holds exactly after a linear
  step). Xsens walk 25 s: σ 1 mm → worst 4.03°, relpos 0.69 cm; 3 mm → 4.01°, 0.82 cm; 10 mm → 5.02°,
  1.08 cm; 30 mm → 7.06°, 1.28 cm (the worst joints are upper-body ones that barely move in that walk).
- Keyframes every 6 samples (10 Hz at 60 Hz): 12 was 2× faster on the walk (9.3 s vs 17.3 s, same
  accuracy) but failed on the fast CMU 131_01 motion (worst 15–20°).
- integration_sigma 1e-2 (position integration noise, `BodyOptions`): 1e-4 on the walk took 30 LM
  iterations (78 s) for the same accuracy as 1e-2 (11 iterations); ≥ 0.3 decouples position from velocity
  and lets the world heading drift (relpos 3.5 cm).
- Preintegration fed with `factors.body.exact_rotation_gyro` (P5): gtsam's tangent-space preintegration is
  first order in |ω dt| per sample (25 rad/s with a turning axis: 1.7–2.6° per keyframe interval), which
  is what made fast arms fail: CMU 131_01, 17 IMUs, no magnetometers, seeds 0–2, RightShoulder joint RMSE
  8.2/10.3/8.8° → 0.32/2.21/0.29°. Extra keyframes keep each interval's turn below 2.5 rad
  (`BodyOptions.max_keyframe_turn_rad`: the preintegrated Log(ΔR) must stay below π).
- Default placement: the nominal site (imugraph.body.placement) rather than bRs = I at mid-segment:
  gaittoolbox walk (offset handling vs Vicon) 5.77° → 5.03° mean, 30 → 14 LM iterations.
- Bias random walk (issue 4) instead of one constant bias per sensor: with a drifting gyro bias the drift
  had nowhere to go but into the joints. benchmarks/body_ablation.py --bias-walk 0.002 (true walk 0.002
  rad/s/√s), worst joint full vs no_joints: constant bias 7.75° vs 3.21° (CMU 131_02), 39.9° vs 4.4° (Xsens);
  bias_rw 2e-4: 5.81° vs 3.21°, 6.39° vs 3.63°; 1e-3: 2.45° vs 3.23°, 2.79° vs 3.44°; 2e-3: 1.81°, 2.30°.
  Without bias walk (constant true bias) 1e-3 was no worse: CMU 1.07° → 0.87°, Xsens 0.92° → 0.62°.
  Gaittoolbox walk (offset handling, mean all): 5.03° (constant), 5.02° (2e-4), 5.01° (1e-3), 5.02° (2e-3).
  Segments of 0.5 s instead of 1 s: no gain (CMU 1.84° vs 1.81° at rw 2e-3).
  Cost: benchmarks/body_speed.py --duration 60 --modes batch (17 IMUs, constant true biases): 12.1 s wall,
  worst joint 1.76° (bias_rw 1e-3) vs 12.8 s, 1.39° (constant bias model); 5e-4: 12.0 s, 1.62°.
- COLAMD ordering: 9.3 s vs 19.0 s with METIS (walk, 25 s). LM relative tolerance 1e-3: on a 20 s walk the
  cost plateaus after 4 iterations (125.5 → 124.8 in 35 more, accuracy unchanged).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph.body.placement_motion import with_motion_placements
from imugraph.errors import SessionError
from imugraph.factors import body as bf
from imugraph.factors import knee_sta
from imugraph.graphs import body_axial, body_chain, body_neck
from imugraph.graphs.body_init import initial_orientations, initial_values, nominal_levers
from imugraph.graphs.body_model import (BodyJoint, BodyOptions, bias_segments, body_joints,  # noqa: F401
                                        check_session, keyframes, npose_samples, sample_turn, sensor_setup)
from imugraph.graphs.body_output import BodyResult  # noqa: F401  (re-exported: the public result type)


@dataclass
class BodyProblem:
    """Everything needed to emit the graph keyframe by keyframe (batch and incremental share it)."""
    session: object
    skel: object
    opts: BodyOptions
    names: list            # sensed segments, topological order, names[0] = root
    joints: list           # BodyJoint
    setups: dict           # name -> SensorSetup
    levers: list           # (segment, joint index, nominal s_l)
    kf: np.ndarray         # keyframe sample indices
    npose_idx: np.ndarray
    npose_method: str
    pims: dict             # name -> list of PreintegratedImuMeasurements (len K-1)
    init: gtsam.Values
    bRs_fixed: dict | None = None      # for hinge factors (second pass)
    mag_dirs: dict | None = None       # per-sensor field direction n_m(s) (use_mag)
    mag_sigmas: dict | None = None     # per-sensor σ of the field direction (B5'; None: BodyOptions.mag_sigma)
    mag_active: bool = True            # False during the magnetometer-free first pass (mag_sigma_ml)
    bias_seg: np.ndarray | None = None  # (K,) bias segment of each keyframe (body_model.bias_segments)
    chains: list | None = None         # unsensed links as segments (body_chain, second pass; None: lumped)
    chain_place: dict | None = None    # first-pass placements {seg: (bRs, b_pos)} the chain factors use
    chain_targets: dict | None = None  # first-pass ties per link (body_chain.tie_targets, unsensed_prior "fixed")
    chain_angles: dict | None = None   # first-pass bend θ_k per link (body_chain.tie_angles, unsensed_sigma_gain)
    bend_values: gtsam.Values | None = None  # (N9) body_neck.mag_free_levers' solution the bend is read from; None: x
    init_motion: dict | None = None    # BodyOptions.init "motion"/"auto": (H3) δ, RMS per child, (H4) ψ (placement_motion)

    def bkey(self, s: int, k: int) -> int:
        """Bias key of sensor s used by the ImuFactor from keyframe k to k+1."""
        return bf.bias_key(s, int(self.bias_seg[k]) if self.bias_seg is not None else 0)

    @property
    def kf_t(self) -> np.ndarray:
        return np.asarray(self.session.t, float)[self.kf]

    @property
    def K(self) -> int:
        return int(self.kf.size)


def build_problem(session, opts: BodyOptions = BodyOptions()) -> BodyProblem:
    """Set up the body problem: joints, noise, N-pose, preintegration, initial values."""
    check_session(session)
    skel = session.skeleton
    if skel is None:
        raise SessionError(session.source, "skeleton", "None", "a Skeleton (imugraph.body.skeleton)")
    names = sorted(skel.sensed, key=skel.index)
    if skel.index(names[0]) != 0:
        raise SessionError(session.source, "skeleton.sensed", f"root '{skel.names[0]}' unsensed", "a sensed root")
    joints = body_joints(skel) if opts.use_joints else []
    npose_idx, method = npose_samples(session, opts)
    opts, init_motion = with_motion_placements(session, opts, npose_idx)     # init "motion": (H1)–(H4); else as is
    setups = sensor_setup(session, skel, opts, npose_idx)
    turn = sample_turn(session, names, setups) if opts.max_keyframe_turn_rad is not None else None
    kf = keyframes(session.t.size, opts.keyframe_every, turn, opts.max_keyframe_turn_rad)
    init_mag = opts.init_heading_from_mag
    if init_mag is None:
        init_mag = opts.use_mag or all(np.all(np.isfinite(session.sensors[n].mag[npose_idx]), axis=1).any() for n in names)
    nRs = initial_orientations(session, names, setups, npose_idx, np.deg2rad(opts.npose_heading_deg), init_mag)
    levers = nominal_levers(joints, setups)
    t = np.asarray(session.t, float)
    bias_seg = bias_segments(t[kf], opts.bias_segment_s if opts.bias_rw is not None else None)
    init = initial_values(names, joints, levers, {n: nRs[n][kf] for n in names}, t[kf], setups,
                          int(bias_seg.max()) + 1)
    pims = {name: sensor_pims(session.sensors[name], setups[name], kf, opts) for name in names}
    return BodyProblem(session, skel, opts, names, joints, setups, levers, kf, npose_idx, method, pims, init,
                       bias_seg=bias_seg, init_motion=init_motion)


def sensor_pims(s, st, kf: np.ndarray, opts: BodyOptions):
    """One sensor's gyro/acc preintegrated between keyframes kf, from its setup's noise and start gyro bias."""
    prm = bf.imu_params(opts.g, st.sigma_gyr, st.sigma_acc, float(np.median(s.dt)), opts.integration_sigma)
    return bf.preintegrate(s.gyr, s.acc, s.dt, kf, prm, gtsam.imuBias.ConstantBias(np.zeros(3), st.gyro_bias0))


def _joint_model(pb: BodyProblem, jt: BodyJoint):
    if jt.lumped:
        return gtsam.noiseModel.Isotropic.Sigma(3, pb.opts.lumped_joint_sigma_m)
    if pb.opts.joint_sigma_m is None:
        return gtsam.noiseModel.Constrained.All(3)
    return gtsam.noiseModel.Isotropic.Sigma(3, pb.opts.joint_sigma_m)


def _mag_direction(pb: BodyProblem, name: str, values: gtsam.Values) -> np.ndarray:
    """Per-sensor field direction n_m(s): N-pose mean of nRs·b_mag/|b_mag| at the initial orientations."""
    s = pb.names.index(name)
    mag = pb.session.sensors[name].mag
    acc = []
    for k in range(pb.K):
        i = pb.kf[k]
        if i > pb.npose_idx[-1]:
            break
        if np.all(np.isfinite(mag[i])):
            acc.append(values.atPose3(bf.pose_key(s, k)).rotation().matrix() @ (mag[i] / np.linalg.norm(mag[i])))
    d = np.mean(acc, axis=0) if acc else np.array([1.0, 0.0, 0.0])
    return d / np.linalg.norm(d)


def mag_noise(pb: BodyProblem, values: gtsam.Values, sigma_floor: float) -> dict:
    """(B5') per-sensor σ of the field direction, by maximum likelihood at a solution `values`.

    With the sensor orientations nRs_k of that solution and the sensor's N-pose field direction n_m(s)
    (pb.mag_dirs, from the initial N-pose orientations, which take their headings from the magnetometers),
        σ_m(s)² = Σ_k ‖s_kRn n_m(s) − b̂_k‖² / (2 K)        (b̂ unit vectors: two degrees of freedom each),
    floored at `sigma_floor`. A magnetometer that sees a field that is not constant in the navigation frame
    (iron near the floor at a foot, a distorted sensor: the real walk's left shank spreads 37° RMS) thus gets a
    weight that matches what it explains, instead of turning its segment. (The direction itself re-estimated
    at the solution instead — the trial mean, or the N-pose mean at the solution — locks in the magnetometer-free
    pass's relative heading errors: CMU 131_01 seed 3 RightShoulder 1.70° → 2.02–2.12°.)"""
    sigmas = {}
    for s, name in enumerate(pb.names):
        mag = pb.session.sensors[name].mag[pb.kf]
        ok = np.all(np.isfinite(mag), axis=1) & (np.linalg.norm(np.nan_to_num(mag), axis=1) > 0)
        if not ok.any():
            sigmas[name] = float("inf")
            continue
        b_hat = mag[ok] / np.linalg.norm(mag[ok], axis=1, keepdims=True)
        nRs = np.stack([values.atPose3(bf.pose_key(s, k)).rotation().matrix() for k in np.flatnonzero(ok)])
        r = np.einsum("kji,j->ki", nRs, pb.mag_dirs[name]) - b_hat
        sigmas[name] = max(sigma_floor, float(np.sqrt(np.sum(r * r) / (2 * len(r)))))
    return sigmas


def factors_at(pb: BodyProblem, k: int) -> gtsam.NonlinearFactorGraph:
    """All factors whose newest keyframe is k (k = 0 also carries the priors on global variables)."""
    o = pb.opts
    g = gtsam.NonlinearFactorGraph()
    if k == 0:
        for s, name in enumerate(pb.names):
            st = pb.setups[name]
            g.add(gtsam.PriorFactorConstantBias(pb.bkey(s, 0), gtsam.imuBias.ConstantBias(np.zeros(3), st.gyro_bias0),
                  gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, o.acc_bias_sigma), np.full(3, o.gyro_bias_sigma)])))
            T0 = pb.init.atPose3(bf.pose_key(s, 0))
            if s == 0:
                g.add(bf.yaw_information_prior(bf.pose_key(s, 0), T0, 1e-3, o.root_heading_sigma_rad, o.tilt_sigma_rad))
            else:
                yaw = o.heading_sigma_rad if o.heading_sigma_rad is not None else 1e3
                g.add(bf.yaw_information_prior(bf.pose_key(s, 0), T0, 10.0, yaw, o.tilt_sigma_rad))
            g.add(gtsam.PriorFactorVector(bf.vel_key(s, 0), np.zeros(3),
                                          gtsam.noiseModel.Isotropic.Sigma(3, o.start_velocity_sigma)))
        if o.lever_sigma_m is not None:
            lever_model = gtsam.noiseModel.Isotropic.Sigma(3, o.lever_sigma_m)
            for i, (_, _, l_nom) in enumerate(pb.levers):
                g.add(gtsam.PriorFactorPoint3(bf.lever_key(i), l_nom, lever_model))
        if o.use_mag and pb.mag_dirs is None:
            pb.mag_dirs = {n: _mag_direction(pb, n, pb.init) for n in pb.names}
    else:
        for s, name in enumerate(pb.names):
            g.add(gtsam.ImuFactor(bf.pose_key(s, k - 1), bf.vel_key(s, k - 1), bf.pose_key(s, k), bf.vel_key(s, k),
                                  pb.bkey(s, k - 1), pb.pims[name][k - 1]))
        if pb.bkey(0, k) != pb.bkey(0, k - 1):
            g.push_back(bias_walk_factors(pb, k))
    lever_index = {(seg, j): i for i, (seg, j, _) in enumerate(pb.levers)}
    chained = body_chain.chain_joints(pb)
    for j, jt in enumerate(pb.joints):
        P, C = pb.names.index(jt.parent), pb.names.index(jt.child)
        fs = bf.joint_factors(bf.joint_key(j, k), bf.pose_key(P, k), bf.lever_key(lever_index[(jt.parent, j)]),
                              bf.pose_key(C, k), bf.lever_key(lever_index[(jt.child, j)]), _joint_model(pb, jt))
        for f in (fs[1:] if j in chained else fs):      # chained: the parent side is body_chain's (C1)–(C3)
            g.add(f)
    if chained:
        g.push_back(body_chain.chain_factors_at(pb, k, pb.chain_place))
    if o.use_mag and pb.mag_active:
        for s, name in enumerate(pb.names):
            m = pb.session.sensors[name].mag[pb.kf[k]]
            if np.all(np.isfinite(m)) and np.linalg.norm(m) > 0:
                sigma = pb.mag_sigmas[name] if pb.mag_sigmas else o.mag_sigma
                g.add(bf.mag_factor(bf.pose_key(s, k), m / np.linalg.norm(m), 1.0, pb.mag_dirs[name],
                                    gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
    if pb.bRs_fixed is not None:
        hm = gtsam.noiseModel.Isotropic.Sigma(2, o.hinge_sigma_rad)
        g.push_back(body_axial.axial_factors_at(pb, k))       # soft axial rotations (S2), their hinges (S3)
        g.push_back(knee_sta.factors_at(pb, k))               # thigh turn ∝ knee flexion (G1)-(G3), off by default
        for jt in pb.joints:
            if jt.child in o.hinges and not body_axial.axial_joint(pb, jt) and not knee_sta.handles(pb, jt):
                P, C = pb.names.index(jt.parent), pb.names.index(jt.child)
                g.add(bf.hinge_factor(hm, bf.pose_key(P, k), bf.pose_key(C, k),
                                      pb.bRs_fixed[jt.parent].T, pb.bRs_fixed[jt.child].T))
    return g


def bias_walk_factors(pb: BodyProblem, k: int) -> gtsam.NonlinearFactorGraph:
    """Random-walk link into the bias segment that starts at keyframe k: b_m − b_{m−1} ~ N(0, rw² Δt I),
    Δt = time between the two segments' first keyframes (gyro rw = opts.bias_rw, acc rw = opts.acc_bias_rw)."""
    o, g = pb.opts, gtsam.NonlinearFactorGraph()
    seg = pb.bias_seg
    k_prev = int(np.flatnonzero(seg == seg[k - 1])[0])
    dt = float(pb.kf_t[k] - pb.kf_t[k_prev])
    model = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, o.acc_bias_rw), np.full(3, o.bias_rw)] * np.sqrt(dt))
    zero = gtsam.imuBias.ConstantBias()
    for s in range(len(pb.names)):
        g.add(gtsam.BetweenFactorConstantBias(pb.bkey(s, k - 1), pb.bkey(s, k), zero, model))
    return g


def full_graph(pb: BodyProblem) -> gtsam.NonlinearFactorGraph:
    g = gtsam.NonlinearFactorGraph()
    for k in range(pb.K):
        g.push_back(factors_at(pb, k))
    return g


def python_lm(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int, rel_tol: float,
              ordering: gtsam.Ordering) -> tuple[gtsam.Values, int]:
    """Levenberg–Marquardt driven from Python (for graphs with CustomFactors): (A + λI)δ = b per iteration."""
    x, cost, lam = gtsam.Values(values), graph.error(values), 1e-3
    dims = [(key, bf.key_dim(key)) for key in values.keys()]
    it = 0
    for it in range(1, max_iterations + 1):
        gfg = graph.linearize(x)
        while True:
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(gfg)
            for key, d in dims:
                damped.push_back(gtsam.JacobianFactor(key, np.sqrt(lam) * np.eye(d), np.zeros(d),
                                                      gtsam.noiseModel.Unit.Create(d)))
            x_new = x.retract(damped.optimize(ordering))
            new = graph.error(x_new)
            if new <= cost or lam > 1e8:
                break
            lam *= 10.0
        if new > cost:
            break
        done = cost - new <= rel_tol * max(cost, 1e-300)
        x, cost, lam = x_new, new, max(lam / 10.0, 1e-9)
        if done:
            break
    return x, it


def optimize(pb: BodyProblem, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> tuple[gtsam.Values, dict]:
    """LM on the body graph: gtsam's C++ optimizer, or the Python loop when hinge CustomFactors are present."""
    t0 = time.perf_counter()
    if pb.bRs_fixed is not None and pb.opts.hinges:
        ordering = (gtsam.Ordering.MetisNonlinearFactorGraph if pb.opts.ordering == "metis"
                    else gtsam.Ordering.ColamdNonlinearFactorGraph)(graph)
        x, iters = python_lm(graph, values, pb.opts.max_iterations, pb.opts.relative_tol, ordering)
    else:
        prm = gtsam.LevenbergMarquardtParams()
        prm.setMaxIterations(pb.opts.max_iterations)
        prm.setRelativeErrorTol(pb.opts.relative_tol)
        prm.setOrderingType(pb.opts.ordering.upper())
        prm.setlambdaInitial(1e-2)       # smaller λ: the near-free global translation makes the
        prm.setlambdaLowerBound(1e-3)    # undamped system numerically indefinite (rejected trial steps)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, prm)
        x = opt.optimize()
        iters = opt.iterations()
    return x, {"iterations": int(iters), "cost_initial": float(graph.error(values)),
               "cost_final": float(graph.error(x)), "seconds": time.perf_counter() - t0}


def solve_body_incremental(session, opts: BodyOptions = BodyOptions(), lag_s: float | None = None, **kwargs):
    """iSAM2 (lag_s None) or fixed-lag smoothing on the same graph: imugraph.graphs.body_incremental."""
    from imugraph.graphs.body_incremental import solve_body_incremental as run
    return run(session, opts, lag_s, **kwargs)


def optimize_with_mag_noise(pb: BodyProblem) -> tuple[gtsam.Values, list, gtsam.NonlinearFactorGraph]:
    """LM from pb.init; with magnetometers and BodyOptions.mag_sigma_ml, first without them, then with each
    sensor's σ from that solution (mag_noise, B5'), warm-started, σ re-estimated as mag_sigma_ml says.
    Returns (estimate, pass infos, the last pass's graph)."""
    passes, x = [], pb.init
    rounds = int(pb.opts.mag_sigma_ml) if pb.opts.use_mag else 0
    if rounds:
        pb.mag_active = False                         # first pass: inertial sensors and the body model only
        x, info = optimize(pb, full_graph(pb), x)
        passes.append(info)
        pb.mag_sigmas = mag_noise(pb, x, pb.opts.mag_sigma)   # pb.mag_dirs: set by factors_at(k=0), N-pose
        pb.mag_active = True
    while True:
        graph = full_graph(pb)
        x, info = optimize(pb, graph, x)
        passes.append(info)
        rounds -= 1
        if rounds <= 0:
            return x, passes, graph
        sigmas = mag_noise(pb, x, pb.opts.mag_sigma)   # re-estimated at the solution with magnetometers
        finite = [n for n in pb.names if np.isfinite(sigmas[n]) and np.isfinite(pb.mag_sigmas[n])]
        changed = max((abs(np.log(sigmas[n] / pb.mag_sigmas[n])) for n in finite), default=0.0)
        if changed < np.log(1.1):
            return x, passes, graph                    # pb.mag_sigmas: the σ this solution used
        pb.mag_sigmas = sigmas


def chain_pass(pb: BodyProblem, x: gtsam.Values) -> tuple[gtsam.Values, dict, gtsam.NonlinearFactorGraph]:
    """Second pass with the unsensed links as segments (body_chain), warm-started from the first pass `x`,
    whose N-pose placements give the sensor-to-segment rotations of (C4)."""
    from imugraph.graphs.body_output import estimate_placements
    pb.chain_place = estimate_placements(pb, x)[0]
    pb.chains = body_chain.make_chains(pb, pb.chain_place)
    pb.chain_targets = body_chain.tie_targets(pb, x, pb.chain_place) if pb.opts.unsensed_prior == "fixed" else None
    pb.chain_angles = body_chain.tie_angles(pb, x, pb.chain_place) if pb.opts.unsensed_sigma_gain is not None else None
    graph = full_graph(pb)
    x, info = optimize(pb, graph, body_chain.insert_initial(pb, x, pb.chain_place))
    return x, info, graph


def solve_body_batch(session, opts: BodyOptions = BodyOptions()) -> BodyResult:
    """Batch LM over the whole session: a `BodyResult` with all skeleton segments at every input sample."""
    from imugraph.graphs.body_output import estimate_placements, make_result
    t0 = time.perf_counter()
    pb = build_problem(session, opts)
    t_build = time.perf_counter() - t0
    x, passes, graph = optimize_with_mag_noise(pb)
    if opts.unsensed_sigma_rad is not None and any(jt.lumped for jt in pb.joints):
        x, info2, graph = chain_pass(pb, x)                # the unsensed links as estimated segments (C1)–(C6)
        passes.append(info2)
    elif opts.lever_prior_frame in ("estimated", "lumped"):  # lever priors in the estimated frames (body_neck N6)
        x, info2 = body_neck.lever_pass(pb, x, graph)
        if info2 is not None:
            passes.append(info2)
    if opts.hinges:
        pb.bRs_fixed = {n: p[0] for n, p in estimate_placements(pb, x)[0].items()}
        if opts.knee_gain_segments:
            knee_sta.prepare(pb, x)                           # κ_k from the hinge-free pass (G1)
        graph = full_graph(pb)
        x, info2 = optimize(pb, graph, knee_sta.insert_initial(pb, body_axial.insert_initial(pb, x)))
        passes.append(info2)
    info = {"build_s": t_build, "passes": passes, "keyframes": pb.K, "npose": pb.npose_method,
            "factors": int(graph.size()), "solve_s": sum(p["seconds"] for p in passes)}
    if pb.mag_sigmas:
        info["mag_sigmas"] = dict(pb.mag_sigmas)
    if pb.init_motion is not None:
        info["init_motion"] = pb.init_motion
    res = make_result(pb, x, info)
    if opts.knee_gain_segments:
        knee_sta.apply_to_result(pb, x, res)                  # nRb = nRs bRsᵀ Exp(−θ â), θ = c + g κ (G1)
    return res
