"""Base fit of a body session and its residuals per sensor × channel (docs/diagnose_body.md §1).

The user's model is the body graph of imugraph.graphs.body with its DEFAULT options (rigid sensors on rigid
segments, joints σ 3 mm, lever-arm priors, per-sensor bias random walk, no magnetometers), solved by its batch
LM (build_problem → full_graph → optimize → make_result, exactly as `solve_body_batch`). The residuals are the
ones that graph itself has, per sensor s and keyframe interval k = [a, b) (T_k = t_b − t_a, samples i ∈ [a, b)):

    ΔR̃_k = Π_i Exp((ỹ_g,i − b̂_g,k) dt_i),   Δṽ_k = Σ_i ΔR̃_a→i (ỹ_a,i − b̂_a,k) dt_i        (preintegration)
    gyr_k   = Log((R̂_aᵀ R̂_b)ᵀ ΔR̃_k) / T_k                     rad/s, sensor frame         (BR1)
    acc_k   = (Δṽ_k − R̂_aᵀ (v̂_b − v̂_a − g_n T_k)) / T_k          m/s², sensor frame at a     (BR2)
    pos_k   = 2 (Δp̃_k − R̂_aᵀ (p̂_b − p̂_a − v̂_a T_k − ½ g_n T_k²)) / T_k²    m/s², sensor frame at a  (BR2')
    joint_k = [R̂_aᵀ (Ĵ_j,a − p̂_a) − l̂_j]_j                        m, one 3-block per lever    (BR3)

and one per-sample residual the rigid model implies at the full rate (Seel et al.'s joint-acceleration
constraint: two sensors on the segments of joint j must see the same acceleration of the joint centre):

    ĵ_s,i  = (ỹ_a,i − b̂_a) + Exp(ω_i dt_i/2) (ω̇_i × l̂_j + ω_i × (ω_i × l̂_j)),   ω = ỹ_g − b̂_g, ω̇ by
             central differences; the lever term turned to mid-sample: the rate is the sample interval's
             and the specific force is held in the frame at its start (the discrete model of the graph's
             preintegration; without the turn, 0.35 m/s² RMS disagreement across a noiseless knee at 60 Hz)
    jacc_i = [ĵ_s,i − R̂_s,iᵀ R̂_q,i ĵ_q,i]_j      m/s², sensor s's frame, one 3-block per joint (s, q)   (BR4)

(R̂_s,i: the fitted per-sample sensor orientation, segment ∘ placement; ĵ_q with the neighbour's own lever
to the same joint). A sensor moving on its segment by d(t) (soft tissue) leaves its orientation fitted and
its position bent, but puts d̈ + 2ω × ḋ + ω̇ × d + ω × (ω × d) into (BR4) sample by sample, at frequencies
the keyframe residuals average away.

(R̂, p̂, v̂: fitted sensor pose and velocity at the keyframes, graph frame, g_n = (0, 0, −g); Ĵ_j: fitted joint
centre; l̂_j: fitted lever arm of the sensor to joint j). (BR1)–(BR2) are the IMU factor's rotation and velocity
errors as mean rates (a gyro or accelerometer change Δ enters them as its interval mean, to first order),
(BR2') its position error as the constant acceleration that would close it (Δp̃_k = Σ_i [Δṽ_a→i dt_i +
½ ΔR̃_a→i (ỹ_a,i − b̂_a) dt_i²]); the position error carries most of the misfit: the graph's integration noise
(σ 1e-2) lets positions move against the accelerometer where the joints pull (measured on a simulated walk:
velocity-rate residual RMS ≈ 1e-4 m/s², joint residual ≈ 0.03 mm). (BR3) is the joint factor's error in the
sensor frame. Between keyframes the fit integrates the sensor, so there is
no per-sample residual: the keyframe interval is the residual's sample (t_k = t_a).

Fitted model for the simulation: the segment motion of the result (`BodyResult.n_quat`, `n_pos`: rigid, the
joints hold exactly by forward kinematics), the fitted sensor-to-segment poses (`placements`), the fitted
bias paths (per sample, the bias of the sample's keyframe) and the model's white noise σ (the N-pose rest's,
`SensorSetup.sigma_gyr/acc`, as the graph uses).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import expmap, logmap

CHANNELS = ("gyr", "acc", "pos", "joint", "jacc")
SAMPLE_CHANNELS = ("jacc",)            # per sample (time base session.t); the others per keyframe interval


@dataclass
class SensorFit:
    """One sensor's part of the base fit.

    Attributes:
        name: segment name. t: (K−1,) residual times (start of each keyframe interval), s.
        residuals: channel → (K−1, d) raw residuals (BR1)–(BR3) (joint: d = 3 × number of levers).
        R_kf, p_kf, v_kf: (K, 3, 3), (K, 3), (K, 3) fitted sensor pose/velocity at the keyframes (graph frame).
        levers: (L, 3) fitted lever arms (joint centres in the sensor frame), joint_names: their joints.
        b_gyr, b_acc: (N, 3) fitted bias per sample. sigma_gyr, sigma_acc: (3,) model white noise per sample.
        bRs, b_pos: fitted sensor-to-segment pose. long_axis: (3,) the segment's long axis in the sensor frame.
        t_sample: (N,) sample times (time base of SAMPLE_CHANNELS). R_samples: (N, 3, 3) fitted nRs per sample.
        pairs: per joint of the sensor (BR4): {"joint", "other", "lever", "n_j_other" (N, 3): R̂_q ĵ_q}.
    """

    name: str
    t: np.ndarray
    residuals: dict
    R_kf: np.ndarray
    p_kf: np.ndarray
    v_kf: np.ndarray
    levers: np.ndarray
    joint_names: list
    b_gyr: np.ndarray
    b_acc: np.ndarray
    sigma_gyr: np.ndarray
    sigma_acc: np.ndarray
    bRs: np.ndarray
    b_pos: np.ndarray
    long_axis: np.ndarray
    t_sample: np.ndarray = None
    R_samples: np.ndarray = None
    pairs: list = field(default_factory=list)

    def time_base(self, channel: str) -> np.ndarray:
        return self.t_sample if channel in SAMPLE_CHANNELS else self.t


@dataclass
class BodyFit:
    """The base fit of a body session: the solver's result, per-sensor fits, keyframes and timing."""

    session: object
    result: object
    kf: np.ndarray
    sensors: dict                       # name → SensorFit
    g: float
    info: dict = field(default_factory=dict)
    problem: object = field(default=None, repr=False)    # the body problem (graphs.body.BodyProblem) solved
    values: object = field(default=None, repr=False)     # its solution (gtsam.Values): warm starts (refit)
    graph: object = field(default=None, repr=False)      # its graph (full_graph(problem)): reused by warm refits

    @property
    def names(self) -> list:
        return list(self.sensors)

    def residuals(self, name: str) -> dict:
        return self.sensors[name].residuals


def _interval_preintegration(gyr, acc, dt, kf, b_g, b_a):
    """(K−1, 3, 3) ΔR̃, (K−1, 3) Δṽ and Δp̃ per keyframe interval (module doc), vectorised over intervals:
    sample m of every interval at once; the specific force of a sample is held in the frame at its start."""
    a, b = kf[:-1], kf[1:]
    L = b - a
    n = a.size
    dR = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    dv = np.zeros((n, 3))
    dp = np.zeros((n, 3))
    for m in range(int(L.max())):
        act = np.flatnonzero(L > m)
        i = a[act] + m
        h = dt[i][:, None]
        f = np.einsum("nab,nb->na", dR[act], acc[i] - b_a[act])
        dp[act] += dv[act] * h + 0.5 * f * h**2
        dv[act] += f * h
        dR[act] = dR[act] @ expmap((gyr[i] - b_g[act]) * h)
    return dR, dv, dp


def sensor_residuals(gyr, acc, dt, kf, t, R_kf, p_kf, v_kf, b_g_kf, b_a_kf, g, J_kf, levers) -> dict:
    """channel → (K−1, d) residuals (BR1)–(BR3) of one sensor for measurements gyr, acc (N, 3).

    b_g_kf, b_a_kf: (K, 3) fitted biases per keyframe (the interval k uses keyframe k's); J_kf: (K, L, 3) the
    joint centres of the sensor's L levers, levers (L, 3)."""
    T = (t[kf[1:]] - t[kf[:-1]])[:, None]
    dR, dv, dp = _interval_preintegration(gyr, acc, dt, kf, b_g_kf[:-1], b_a_kf[:-1])
    Ra, Rb = R_kf[:-1], R_kf[1:]
    rel = np.einsum("nba,nbc->nac", Ra, Rb)                                    # R̂_aᵀ R̂_b
    r_gyr = logmap(np.einsum("nba,nbc->nac", rel, dR)) / T                     # (BR1)
    g_n = np.array([0.0, 0.0, -g])
    dv_model = np.einsum("nba,nb->na", Ra, v_kf[1:] - v_kf[:-1] - g_n * T)
    r_acc = (dv - dv_model) / T                                                # (BR2)
    dp_model = np.einsum("nba,nb->na", Ra, p_kf[1:] - p_kf[:-1] - v_kf[:-1] * T - 0.5 * g_n * T**2)
    r_pos = 2.0 * (dp - dp_model) / T**2                                       # (BR2')
    if levers.shape[0]:
        d = J_kf[:-1] - p_kf[:-1, None, :]                                     # (K−1, L, 3)
        r_joint = (np.einsum("nba,nlb->nla", Ra, d) - levers[None]).reshape(len(Ra), -1)   # (BR3)
    else:
        r_joint = np.zeros((len(Ra), 0))
    return {"gyr": r_gyr, "acc": r_acc, "pos": r_pos, "joint": r_joint}


def joint_acceleration(t, gyr, acc, b_g, b_a, lever) -> np.ndarray:
    """(N, 3) ĵ of (BR4): the joint centre's specific-force-like acceleration seen from one sensor."""
    w = gyr - b_g
    wd = np.gradient(w, t, axis=0)
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2]))
    arm = np.cross(wd, lever) + np.cross(w, np.cross(w, lever))
    return (acc - b_a) + np.einsum("nab,nb->na", expmap(w * (0.5 * dt)[:, None]), arm)


def jacc_residuals(sf: "SensorFit", t, gyr, acc) -> np.ndarray:
    """(N, 3·P) residual (BR4) of one sensor for measurements gyr, acc (its neighbours' terms fixed)."""
    if not sf.pairs:
        return np.zeros((t.size, 0))
    out = [joint_acceleration(t, gyr, acc, sf.b_gyr, sf.b_acc, p["lever"])
           - np.einsum("nba,nb->na", sf.R_samples, p["n_j_other"]) for p in sf.pairs]
    return np.concatenate(out, axis=1)


def long_axis_in_sensor(skel, name: str, bRs: np.ndarray) -> np.ndarray:
    """The segment's long axis (origin → distal end, `Skeleton.ends`) in the sensor frame: bRsᵀ e."""
    e = np.asarray(skel.ends[skel.index(name)], float)
    e = e / np.linalg.norm(e) if np.linalg.norm(e) > 1e-9 else np.array([0.0, 0.0, 1.0])
    return bRs.T @ e


def fit_body(session, opts=None, chunk_s: float | None = None, lm: tuple | None = None) -> BodyFit:
    """The base fit (module doc): the body graph's batch LM with `opts` (default: BodyOptions()). chunk_s: LM
    starts from the chunked warm start of body/chunked.py (same graph and optimum; None: from pb.init).
    lm: (λ_initial, λ_min) of LM (body/lm.py; None: graphs.body.optimize's), kept in info["lm"] so that the
    simulations and refits started from this fit solve alike."""
    from imugraph.diagnose.body.lm import lm_optimize
    from imugraph.graphs.body import build_problem, full_graph, optimize
    from imugraph.graphs.body_model import BodyOptions
    from imugraph.graphs.body_neck import single_pass_options

    opts = single_pass_options(BodyOptions() if opts is None else opts)       # one pass: the neck by the ties (K2)
    if getattr(session, "skeleton", None) is None or not getattr(session, "sensors", None):
        raise SessionError(getattr(session, "source", "<memory>"), "skeleton",
                           "a session without skeleton or sensors", "a body session (imugraph.io.body_session)")
    t0 = time.perf_counter()
    pb = build_problem(session, opts)
    graph = full_graph(pb)
    start, chunk_its = pb.init, None
    if chunk_s is not None:
        from imugraph.diagnose.body.chunked import chunked_start
        start, chunk_its = chunked_start(pb, graph, float(chunk_s), optimize)
    x, info = lm_optimize(pb, graph, start, lm)
    if chunk_its is not None:
        info = dict(info, chunk_iterations=chunk_its, chunk_s=float(chunk_s))
    return _extract(session, pb, x, info, t0, graph)


def problem_graph(bfit: BodyFit):
    """A copy of the graph bfit was solved on (the factors shared, the container new: a caller may replace
    factors), or full_graph(problem) when it was not kept."""
    import gtsam

    from imugraph.graphs.body import full_graph

    return full_graph(bfit.problem) if bfit.graph is None else gtsam.NonlinearFactorGraph(bfit.graph)


def graph_with_sensor(graph0, pb, sensor: str):
    """full_graph(pb) for a problem pb that differs from the one `graph0` was built for ONLY in `sensor`'s setup
    and preintegration (fit.refit_body_warm): a copy of graph0 with that sensor's factors replaced — its bias
    prior at k = 0 (the setup's start gyro bias) and its K − 1 ImuFactors — at the same positions, so the
    factor order, and with it the elimination ordering and the solution, are those of a fresh full_graph(pb).
    The factors are found by their keys (the prior: the single key B(s, 0); an ImuFactor: X(s,k−1), V(s,k−1),
    X(s,k), V(s,k), B); None when the graph has other factor types on those keys (hinges, chains,
    magnetometers: the caller then builds full_graph) or the count does not match."""
    import gtsam

    from imugraph.factors import body as bf
    from imugraph.graphs.body import factors_at

    o = pb.opts
    if pb.bRs_fixed is not None or pb.chains is not None or o.use_mag:
        return None
    s = pb.names.index(sensor)
    imu_at = {(bf.pose_key(s, k - 1), bf.vel_key(s, k - 1), bf.pose_key(s, k), bf.vel_key(s, k)): k
              for k in range(1, pb.K)}
    prior_key = pb.bkey(s, 0)
    k0 = factors_at(pb, 0)                                   # the new bias prior, built as full_graph builds it
    prior = [k0.at(i) for i in range(k0.size()) if list(k0.at(i).keys()) == [prior_key]]
    g = gtsam.NonlinearFactorGraph(graph0)
    found = 0
    for i in range(g.size()):
        f = g.at(i)
        if f is None:
            continue
        keys = tuple(f.keys())
        if len(keys) == 1 and keys[0] == prior_key and len(prior) == 1:
            g.replace(i, prior[0])
            found += 1
        elif len(keys) == 5 and keys[:4] in imu_at:
            k = imu_at[keys[:4]]
            g.replace(i, gtsam.ImuFactor(*keys[:4], pb.bkey(s, k - 1), pb.pims[sensor][k - 1]))   # as factors_at
            found += 1
    return g if found == pb.K else None


def refit_body_warm(base: BodyFit, session, sensor: str, max_iterations: int | None = None) -> BodyFit:
    """The body graph of `base` re-solved for a session in which ONLY `sensor`'s measurements changed (a
    removed effect, body/refit.py): same keyframes, N-pose window, priors and gauge (built from the base
    problem's initial values, as the base graph's were), the sensor's setup (N-pose noise, gyro bias) and
    preintegration recomputed, every other sensor's preintegration reused, and LM started from the base
    fit's solution (warm start) instead of the gyro-integrated initial orientations. The optimum sought is the
    cold fit's (same graph); measured on the real walk: docs/diagnose_body.md §4."""
    from dataclasses import replace as dc_replace

    from imugraph.diagnose.body.lm import lm_optimize
    from imugraph.graphs.body import full_graph, sensor_pims
    from imugraph.graphs.body_model import sensor_setup

    pb0 = base.problem
    if pb0 is None or base.values is None:
        raise ValueError("refit_body_warm: the base fit keeps no problem/values")
    t0 = time.perf_counter()
    opts = pb0.opts if max_iterations is None else dc_replace(pb0.opts, max_iterations=int(max_iterations))
    setups = dict(pb0.setups)
    setups[sensor] = sensor_setup(session, pb0.skel, opts, pb0.npose_idx)[sensor]
    pims = dict(pb0.pims)
    pims[sensor] = sensor_pims(session.sensors[sensor], setups[sensor], pb0.kf, opts)
    pb = dc_replace(pb0, session=session, opts=opts, setups=setups, pims=pims, mag_dirs=None)
    graph = graph_with_sensor(base.graph, pb, sensor) if base.graph is not None else None
    graph = full_graph(pb) if graph is None else graph
    x, info = lm_optimize(pb, graph, base.values, base.info.get("lm"))         # the base fit's LM damping
    return _extract(session, pb, x, dict(info, warm_start=True), t0, graph)


def _extract(session, pb, x, info: dict, t0: float, graph=None) -> BodyFit:
    """BodyFit (residuals (BR1)–(BR4) per sensor) of the solution x of problem pb."""
    from imugraph.factors import body as bf
    from imugraph.graphs.body_output import make_result

    result = make_result(pb, x, info)
    t = np.asarray(session.t, float)
    owner = np.clip(np.searchsorted(pb.kf, np.arange(t.size), side="right") - 1, 0, pb.K - 1)
    sensors = {}
    for s, name in enumerate(pb.names):
        ses = session.sensors[name]
        poses = [x.atPose3(bf.pose_key(s, k)) for k in range(pb.K)]
        R_kf = np.stack([p.rotation().matrix() for p in poses])
        p_kf = np.stack([np.asarray(p.translation(), float) for p in poses])
        v_kf = np.stack([np.asarray(x.atVector(bf.vel_key(s, k)), float) for k in range(pb.K)])
        bias = [x.atConstantBias(pb.bkey(s, k)) for k in range(pb.K)]
        b_g = np.stack([np.asarray(b.gyroscope(), float) for b in bias])
        b_a = np.stack([np.asarray(b.accelerometer(), float) for b in bias])
        lev = [(i, j) for i, (seg, j, _) in enumerate(pb.levers) if seg == name]
        levers = np.array([np.asarray(x.atPoint3(bf.lever_key(i)), float) for i, _ in lev]).reshape(-1, 3)
        J_kf = np.array([[np.asarray(x.atPoint3(bf.joint_key(j, k)), float) for _, j in lev]
                         for k in range(pb.K)]).reshape(pb.K, len(lev), 3)
        res = sensor_residuals(ses.gyr, ses.acc, ses.dt, pb.kf, t, R_kf, p_kf, v_kf, b_g, b_a, pb.opts.g, J_kf,
                               levers)
        pl = result.placements[name]
        st = pb.setups[name]
        sensors[name] = SensorFit(name, t[pb.kf[:-1]], res, R_kf, p_kf, v_kf, levers,
                                  [pb.joints[j].name for _, j in lev], b_g[owner], b_a[owner],
                                  np.asarray(st.sigma_gyr, float), np.asarray(st.sigma_acc, float),
                                  np.asarray(pl["bRs"], float), np.asarray(pl["b_pos"], float),
                                  long_axis_in_sensor(session.skeleton, name, np.asarray(pl["bRs"], float)))
    _add_joint_accelerations(session, result, pb, sensors, x)
    info = dict(info, seconds=time.perf_counter() - t0, keyframes=int(pb.K), npose=pb.npose_method,
                npose_window=(float(t[pb.npose_idx[0]]), float(t[pb.npose_idx[-1]])))
    return BodyFit(session, result, pb.kf, sensors, float(pb.opts.g), info, problem=pb, values=x, graph=graph)


def _add_joint_accelerations(session, result, pb, sensors: dict, x) -> None:
    """Per-sample orientations, joint pairs and the (BR4) channel of every sensor (in place)."""
    from imugraph.factors import body as bf
    from imugraph.geometry import quat_to_rotmat

    t = np.asarray(session.t, float)
    skel = session.skeleton
    for name, sf in sensors.items():
        sf.t_sample = t
        sf.R_samples = quat_to_rotmat(np.asarray(result.n_quat[:, skel.index(name)], float)) @ sf.bRs
    lever_of = {(seg, j): np.asarray(x.atPoint3(bf.lever_key(i)), float) for i, (seg, j, _) in enumerate(pb.levers)}
    for j, jt in enumerate(pb.joints):
        if (jt.parent, j) not in lever_of or (jt.child, j) not in lever_of:
            continue
        for me, other in ((jt.parent, jt.child), (jt.child, jt.parent)):
            so, ses_o = sensors[other], session.sensors[other]
            j_o = joint_acceleration(t, ses_o.gyr, ses_o.acc, so.b_gyr, so.b_acc, lever_of[(other, j)])
            sensors[me].pairs.append({"joint": jt.name, "other": other, "lever": lever_of[(me, j)],
                                      "n_j_other": np.einsum("nab,nb->na", so.R_samples, j_o)})
    for name, sf in sensors.items():
        ses = session.sensors[name]
        sf.residuals["jacc"] = jacc_residuals(sf, t, ses.gyr, ses.acc)


def residuals_with(bfit: BodyFit, name: str, gyr=None, acc=None) -> dict:
    """(BR1)–(BR2'), (BR4) of sensor `name` for changed measurements (trajectory, biases, levers and the
    neighbours fixed); joint unchanged. Used by the effects to evaluate an extended model's residuals."""
    sf = bfit.sensors[name]
    ses = bfit.session.sensors[name]
    kf = bfit.kf
    b_g = sf.b_gyr[kf]
    b_a = sf.b_acc[kf]
    J = np.zeros((kf.size, 0, 3))
    out = sensor_residuals(ses.gyr if gyr is None else gyr, ses.acc if acc is None else acc, ses.dt, kf,
                           np.asarray(bfit.session.t, float), sf.R_kf, sf.p_kf, sf.v_kf, b_g, b_a, bfit.g, J,
                           np.zeros((0, 3)))
    out["joint"] = sf.residuals["joint"].copy()
    out["jacc"] = jacc_residuals(sf, np.asarray(bfit.session.t, float), ses.gyr if gyr is None else gyr,
                                 ses.acc if acc is None else acc)
    return out
