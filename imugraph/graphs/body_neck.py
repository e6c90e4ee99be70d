"""The unsensed neck's output from the solved graph (options `BodyOptions.unsensed_bend`, `lever_prior_frame`).

The output ties an unsensed link u between its sensed neighbours A (above) and D (below), e.g. the neck
between T8 and the head, by (K2) of imugraph.body.skeleton: nR_u = slerp(nR_A, nR_D, s), s = 1/2 for one link,
while the graph lumps the link into one soft joint whose point is FIXED in A's frame (a rigid neck, its point
the estimated lever l_A,D of A's sensor). With D's origin o_D (18 cm above the neck base on CMU) the two
disagree by ≈ s·θ·|o_D| for a nod θ (7 cm on CMU 131_02). Measured (benchmarks/n21_neck_split.py): no fixed
or data-chosen s reaches 2 cm on CMU 131_01 either (best s = 0.4: 2.55 cm): the simulated neck (CMU
`lowerneck`, MVN Neck) carries a nearly CONSTANT bend relative to T8 during the motion (−7 … −10° about y,
std 2–4°; the Xsens export: 12.7°, constant), straight only in the N-pose. So the output here follows the
graph's own rigid-neck model (N5; not for the CMU L5 between Pelvis and T8: T8 0.6 → 1.5 cm, hence chosen per
segment), and the levers that carry it get priors in the right frame (N6).

(N5) `graph_bend`, unsensed_bend = ("Head",): the link turns with A by the constant rotation that puts D's origin
where the graph's joint point is, d = bRs_A (l_A,D − l_A,up) (A's origin → D's origin in A's segment frame:
the lumped joint's lever minus the lever of A's own proximal joint, both on A's sensor):

    nR_u(t) = nR_A(t) · Rot(o_D → d − o_u)                                                             (N5)

(Rot(a → b): the smallest rotation turning a's direction into b's). The twist about the link is not seen by
any position and stays at A's.

(N6) `lever_pass`, lever_prior_frame = "estimated": the lever priors (B3) of imugraph.graphs.body put the
nominal joint position into the sensor frame with the NOMINAL sensor-to-segment rotation,
l_nom = bRs_nomᵀ (b_joint − b_pos_nom); a sensor turned by up to 30° on its segment (the simulation's
placements; real straps alike) moves that prior mean by up to 0.5·|b_joint − b_pos| (≈ 10 cm for the neck's
29 cm), and where the data leave a lever free (T8 and the head not turning relative to each other: the
Xsens walk) the estimate follows it. A second LM pass, warm-started from the first, uses

    l_nom' = bR̂sᵀ (b_joint − b_pos_nom)                                                               (N6)

with bR̂s the N-pose placement of the first pass (imugraph.graphs.body_output.estimate_placements);
lever_prior_frame = "lumped": only the levers of the lumped joints (T8–Head, Pelvis–T8), the others unchanged.
`lever_pass_lumped_sigma_m`: the lumped joints' σ in that pass (5 mm: CMU 131_02 head better, the Xsens walk's
worse, and a neck on the ties 10° off in benchmarks/n21_neck_checks.py — not recommended);
`lever_pass_iterations` = 1: one LM step (same heads, +16 % instead of +35 % batch CPU).
Measured (docs/results_issue4.md, session 21; benchmarks/body_sim_accuracy.py --neck): worst head over 5 seeds
without/with magnetometers, ties → N5 + N6 "lumped": CMU 131_01 2.61/2.59 → 1.50/1.45 cm, 131_02 8.21/8.20 →
2.25/3.38 cm, Xsens walk 1.88/1.93 → 1.38/1.42 cm; N5 alone leaves the Xsens walk's head at 5.9 cm.

(N8) `bend_joint_sigma`, lever_pass_bend_sigma_m (helper N21b; off by default): in the (N6) pass the lumped joint of
the neck alone gets this σ (5 mm instead of 20), the lumbar one keeps its own, LM run to convergence there
(2–3 steps). Why (benchmarks/n21b_bend_parts.py, truth used only there): the bend's error on CMU 131_02 is a
lever error on T8's side, not of the head sensor nor of T8's placement rotation: d̂ − d splits into bRs_A's part
(≤ 0.1 cm), T8's head lever (+1.8 … +2.3 cm forward on every seed, both magnetometer settings) and T8's own
origin lever l_A,up (−1.5 … +1.0 cm, seed-dependent, +1.1 cm more with magnetometers on seed 1); the head's
lever error carried into T8's frame is ≤ 0.3 cm forward. The forward offset is neither the N-pose keyframes
(lumped σ ×100 before 3 s: unchanged), nor the lever prior (σ 0.5 m: unchanged), nor LM convergence
(relative_tol 1e-5: unchanged); a tighter neck joint lowers it (+1.6 … +1.8 cm), a tighter lumbar joint spoils
the Xsens walk's head (all lumped joints 7.5 mm: 1.40 → 1.84 cm). Measured (body_sim_accuracy --neck
default,neck5, 5 seeds, worst head without/with magnetometers): CMU 131_02 2.26/3.38 → 1.89/3.04 cm, 131_01
1.50/1.45 → 1.39/1.39, Xsens 1.40/1.42 → 1.36/1.44; no segment worse by > 0.07 cm, joints ≤ +0.66°.
(N9) `mag_free_levers`, unsensed_bend_mag_free (helper N21b; off by default): with magnetometers the T8 sensor's
lever to its own lumped (lumbar) joint moves (131_02 seed 1: +0.95 cm forward against −0.20 without), and the
bend with it; the head's orientation relative to T8 is as good as without (mean error ≤ 0.8°, and its field σ
is not the cause: mag_sigma_ml 0 gives the same heads). So (N5) may read the levers of the (N6) graph solved
once more WITHOUT the magnetometer factors, the orientations staying the magnetometer solution's. With (N8)
("neck5mf"): worst head 131_02 2.26/3.38 → 1.89/1.98 cm, 131_01 1.50/1.45 → 1.39/1.40, Xsens 1.40/1.42 →
1.36/1.42; other segments ≤ +0.03 cm, the head itself up to +0.31 cm on a good seed (131_02 s0 mag 1.06 →
1.37); batch +40 % wall with magnetometers (one more LM solve).
(N7) `length_factors`, unsensed_bend_length_sigma_m (helper N21b; off, not recommended): the head point of T8's
levers held at the skeleton's neck length, |bRs_A (l_A,D − l_A,up) − o_u| = |o_D| — fixes the length error
(≈ +1.4 cm) but not the direction (131_02 worst head 2.29/3.46 cm): the bend's error is across the neck.

(N1)–(N4) `choose_split` (hypothesis tested, not an option): the split s chosen from the graph's keyframe
states by the best lever fit,

    p_As,k + R_As,k a + R_u,k(s) o_D  =  p_Ds,k + R_Ds,k l_D  + r_k,     r_k ~ N(0, σ_r² I)          (N1)
    a ~ N(a_nom, σ_l² I),   l_D ~ N(l_D,nom, σ_l² I)                                                  (N2)
    c(s) = min_{a, l_D}  Σ_k |r_k|²/σ_r² + |a − a_nom|²/σ_l² + |l_D − l_D,nom|²/σ_l²               (N3)
    ŝ = argmin_{s ∈ [0, 1]} c(s)   (grid, then a parabola through the best three)                     (N4)

(a the neck base in A's sensor frame, l_D D's origin in D's sensor frame, σ_l = lever_sigma_m,
σ_r = √2·lumped_joint_sigma_m). To first order in the bend φ, s·φ with lever l_D moves D's sensor like s'·φ
with l_D + (s − s')·o_D and a + (s' − s)·o_D (session 16), so c(s) is nearly flat and ŝ is weakly determined
(131_02: 0.04–0.11, best 0; 131_01: 0.11–0.21, best 0.4). Chains of several unsensed links (the lumbar spine)
keep (K2) throughout.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from imugraph.factors import body as bf
from imugraph.geometry import quat_mul, quat_slerp, quat_to_rotmat, rotmat_to_quat


def single_pass_options(opts):
    """`opts` for a path that solves the graph once (the fixed lag, the diagnosis' base fit): (N5) reads the lumped
    joint's levers, which only (N6)'s second batch pass puts under priors in the estimated sensor frame — with the
    nominal-frame priors alone the bend follows the prior's error (Xsens walk head 1.9 → 5.9 cm, session 21) — so
    without that pass the neck keeps the ties (K2). Unchanged when lever_prior_frame is "nominal" (N5 alone, as asked)."""
    if opts.lever_prior_frame == "nominal" or not opts.unsensed_bend:
        return opts
    return dataclasses.replace(opts, unsensed_bend=())


def lever_pass(pb, x, graph=None):
    """(N6): (x, info) of a second LM pass from `x` with the lever priors' means in the estimated sensor frames
    (info None and `x` unchanged when "lumped" finds no lumped joint)
    (pb.levers replaced; magnetometer σ as the first pass left them). `graph`: the first pass's graph, whose
    lever priors are swapped in place (no rebuild); None, or lever_pass_lumped_sigma_m set: rebuilt."""
    from imugraph.graphs.body import full_graph, optimize
    from imugraph.graphs.body_output import estimate_placements
    o = pb.opts
    if o.lever_prior_frame == "lumped" and not any(jt.lumped for jt in pb.joints):
        return x, None                                     # no lumped joint: nothing to move, no pass
    place = estimate_placements(pb, x)[0]
    new, moved = [], {}
    for i, (seg, j, l_nom) in enumerate(pb.levers):
        jt = pb.joints[j]
        if o.lever_prior_frame == "lumped" and not jt.lumped:
            new.append((seg, j, l_nom))                   # "lumped": only the lumped joints' levers move
            continue
        b_joint = jt.b_parent if jt.parent == seg else jt.b_child
        new.append((seg, j, place[seg][0].T @ (np.asarray(b_joint, float) - pb.setups[seg].b_pos_nom)))   # (N6)
        moved[bf.lever_key(i)] = new[-1][2]
    pb.levers = new
    if graph is None or o.lever_pass_lumped_sigma_m is not None or o.lever_sigma_m is None:
        if o.lever_pass_lumped_sigma_m is not None:        # the lumped joints' σ in this pass only
            pb.opts = dataclasses.replace(o, lumped_joint_sigma_m=o.lever_pass_lumped_sigma_m)
        try:
            graph = full_graph(pb)
        finally:
            pb.opts = o
    else:
        model = gtsam.noiseModel.Isotropic.Sigma(3, o.lever_sigma_m)
        todo = dict(moved)
        for i in range(graph.size()):                      # the priors sit among keyframe 0's factors
            keys = graph.at(i).keys()
            if len(keys) == 1 and keys[0] in todo:
                graph.replace(i, gtsam.PriorFactorPoint3(keys[0], todo.pop(keys[0]), model))
                if not todo:
                    break
    bend_pass_factors(pb, graph, place)                                                            # (N8), (N7)
    if o.lever_pass_iterations is not None:
        pb.opts = dataclasses.replace(o, max_iterations=o.lever_pass_iterations)
    try:
        x, info = optimize(pb, graph, x)
        pb.opts = o
        if o.unsensed_bend_mag_free and o.use_mag and o.unsensed_bend:
            pb.bend_values, info["mag_free_iterations"] = mag_free_levers(pb, x, place)             # (N9)
    finally:
        pb.opts = o
    return x, dict(info, lever_prior_frame=o.lever_prior_frame)


def mag_free_levers(pb, x, place: dict):
    """(N9): (values, LM iterations) of the same (N6) graph without the magnetometer factors, from `x`; (N5) reads
    the neck's bend from these (pb.bend_values), the output's orientations stay those of `x`. Measured reason
    (benchmarks/n21b_bend_parts.py): with magnetometers the T8 sensor's lever to its own (lumped, lumbar) joint
    moves (131_02 seed 1: +1.1 cm forward), and the bend with it, while the head's orientation relative to T8 is
    as good as without (its field σ is not the cause: mag_sigma_ml 0 gives the same heads)."""
    from imugraph.graphs.body import full_graph, optimize
    active = pb.mag_active
    pb.mag_active = False
    try:
        graph = full_graph(pb)                                   # pb.levers: (N6)'s priors already
        bend_pass_factors(pb, graph, place)                                                        # (N8), (N7)
        x_nm, info = optimize(pb, graph, x)
    finally:
        pb.mag_active = active
    return x_nm, info["iterations"]


def bend_pass_factors(pb, graph, place: dict) -> None:
    """The (N6) pass's own changes to `graph` (in place) for the lumped joints of pb.opts.unsensed_bend: (N8) their
    σ lever_pass_bend_sigma_m, (N7) the length factors with unsensed_bend_length_sigma_m (each when not None)."""
    o = pb.opts
    if not o.unsensed_bend:
        return
    if o.lever_pass_bend_sigma_m is not None:
        bend_joint_sigma(pb, graph, tuple(o.unsensed_bend), o.lever_pass_bend_sigma_m)                 # (N8)
    if o.unsensed_bend_length_sigma_m is not None:
        graph.push_back(length_factors(pb, place, tuple(o.unsensed_bend), o.unsensed_bend_length_sigma_m))   # (N7)


def bend_joint_sigma(pb, graph, only: tuple, sigma_m: float) -> int:
    """(N8): in `graph` (in place) the joint factors (B2) of the lumped joints of `split_chains(pb, only)` (the
    neck) get σ = sigma_m, the other lumped joints (the lumbar spine) keep lumped_joint_sigma_m; returns how many
    factors were replaced. Measured reason (benchmarks/n21b_bend_parts.py): a tighter neck joint moves the graph's
    head point towards the truth's on CMU 131_02, a tighter lumbar joint spoils the Xsens walk's head."""
    keys = {bf.joint_key(j, k) for j, *_ in split_chains(pb, only) for k in range(pb.K)}
    model, n = gtsam.noiseModel.Isotropic.Sigma(3, sigma_m), 0
    for i in range(graph.size()):
        f = graph.at(i)
        ks = f.keys() if f is not None else []
        if len(ks) == 3 and ks[2] in keys:                  # ReferenceFrameFactorPoint3Pose3(lever, pose, J)
            graph.replace(i, gtsam.ReferenceFrameFactorPoint3Pose3(ks[0], ks[1], ks[2], model))
            n += 1
    return n


def length_factors(pb, place: dict, only: tuple, sigma_m: float) -> gtsam.NonlinearFactorGraph:
    """(N7): per lumped joint j of `split_chains(pb, only)` with A not the root, one factor on A's two levers

        e = |bRs_A (l_A,D − l_A,up) − o_u| − |o_D|,   e ~ N(0, σ²)                                     (N7)

    (the graph's distal point d of (N5) on the sphere of the skeleton's link length |o_D| about the link's base
    o_u, so the lumped joint is a rigid link of known length whose only freedom is its constant bend; bRs_A the
    first pass's N-pose placement, held fixed). Jacobians: ∂e/∂l_A,D = ûᵀ bRs_A = −∂e/∂l_A,up, û = unit(d − o_u)."""
    skel, g = pb.skel, gtsam.NonlinearFactorGraph()
    lev = {(seg, jj): i for i, (seg, jj, _) in enumerate(pb.levers)}
    model = gtsam.noiseModel.Isotropic.Sigma(1, sigma_m)
    for j, A, link, D in split_chains(pb, only):
        up = next((jj for jj, jt in enumerate(pb.joints) if jt.child == A), None)
        if up is None:
            continue                                           # the root: no proximal lever to measure from
        bRs = np.asarray(place[A][0], float)
        o_u = np.asarray(skel.offsets[skel.index(link)], float)
        length = float(np.linalg.norm(skel.offsets[skel.index(D)]))
        kD, kup = bf.lever_key(lev[(A, j)]), bf.lever_key(lev[(A, up)])

        def error(this, values, H, bRs=bRs, o_u=o_u, length=length, kD=kD, kup=kup):
            v = bRs @ (np.asarray(values.atPoint3(kD)) - np.asarray(values.atPoint3(kup))) - o_u
            n = float(np.linalg.norm(v))
            if H is not None:
                J = ((v / max(n, 1e-9)) @ bRs).reshape(1, 3)
                H[0], H[1] = J, -J
            return np.array([n - length])                                                          # (N7)

        g.add(gtsam.CustomFactor(model, [kD, kup], error))
    return g


def split_chains(pb, only: tuple = ()) -> list:
    """[(joint index, A, link, D)] of pb's lumped joints with exactly one unsensed link (e.g. T8, Neck, Head);
    `only`: distal segments D to keep (() = all)."""
    skel, out = pb.skel, []
    for j, jt in enumerate(pb.joints):
        if not jt.lumped or (only and jt.child not in only):
            continue
        link = skel.names[skel.parents[skel.index(jt.child)]]
        if skel.names[skel.parents[skel.index(link)]] == jt.parent:
            out.append((j, jt.parent, link, jt.child))
    return out


def split_cost(pb, x, place: dict, j: int, A: str, D: str, grid: np.ndarray) -> dict:
    """c(s) of (N3) on `grid` for the lumped joint j between A and D; also the fitted levers per s."""
    o = pb.opts
    skel = pb.skel
    sA, sD = pb.names.index(A), pb.names.index(D)
    TA = [x.atPose3(bf.pose_key(sA, k)) for k in range(pb.K)]
    TD = [x.atPose3(bf.pose_key(sD, k)) for k in range(pb.K)]
    RAs = np.stack([T.rotation().matrix() for T in TA])
    RDs = np.stack([T.rotation().matrix() for T in TD])
    dp = np.stack([TD[k].translation() - TA[k].translation() for k in range(pb.K)])        # p_Ds − p_As
    qA = rotmat_to_quat(RAs @ place[A][0].T)                     # segment orientations R_A,k, R_D,k
    qD = rotmat_to_quat(RDs @ place[D][0].T)
    o_D = np.asarray(skel.offsets[skel.index(D)], float)
    lev = {(seg, jj): l for seg, jj, l in pb.levers}
    a_nom = lev[(A, j)] - pb.setups[A].bRs_nom.T @ o_D           # lumped lever moved to the link's origin
    l_nom = lev[(D, j)]
    sig_r = np.sqrt(2.0) * o.lumped_joint_sigma_m
    sig_l = o.lever_sigma_m if o.lever_sigma_m is not None else 1e3
    K = pb.K
    M = np.concatenate([RAs, -RDs], axis=2).reshape(3 * K, 6) / sig_r                        # (N1) in (a, l_D)
    P = np.eye(6) / sig_l
    costs, levers = [], []
    for s in grid:
        RU = quat_to_rotmat(quat_slerp(qA, qD, np.full(K, float(s))))
        y = (dp - RU @ o_D).reshape(-1) / sig_r
        A_ = np.vstack([M, P])
        b_ = np.r_[y, np.r_[a_nom, l_nom] / sig_l]
        th, *_ = np.linalg.lstsq(A_, b_, rcond=None)
        costs.append(float(np.sum((A_ @ th - b_) ** 2)))                                       # (N3)
        levers.append(th)
    return {"grid": [float(s) for s in grid], "cost": costs, "levers": levers}


def _parabola_min(g: np.ndarray, c: np.ndarray) -> float:
    """(N4): the grid's best point refined by the parabola through it and its neighbours (clipped to them)."""
    i = int(np.argmin(c))
    if i == 0 or i == len(g) - 1:
        return float(g[i])
    x0, x1, x2, y0, y1, y2 = g[i - 1], g[i], g[i + 1], c[i - 1], c[i], c[i + 1]
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2 ** 2 * (y0 - y1) + x1 ** 2 * (y2 - y0) + x0 ** 2 * (y1 - y2)) / den
    return float(np.clip(-b / (2 * a), x0, x2)) if a > 0 else float(x1)


def choose_split(pb, x, step: float = 0.05, only: tuple = ("Head",)) -> dict:
    """{"u": ŝ of the first such chain (nan if none), "splits": {link: ŝ}, "profiles": {link: c(s)}} (N4)."""
    from imugraph.graphs.body_output import estimate_placements
    place = estimate_placements(pb, x)[0]
    grid = np.round(np.arange(0.0, 1.0 + 1e-9, step), 6)
    splits, profiles = {}, {}
    for j, A, link, D in split_chains(pb, only):
        prof = split_cost(pb, x, place, j, A, D, grid)
        splits[link] = _parabola_min(grid, np.asarray(prof["cost"]))
        profiles[link] = {"grid": prof["grid"], "cost": prof["cost"]}
    return {"u": next(iter(splits.values()), float("nan")), "splits": splits, "profiles": profiles}


def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R a ∥ b (Rodrigues; a, b nonzero)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + V + V @ V / (1.0 + c)


def graph_bend(pb, x, only: tuple = (), place: dict | None = None) -> dict:
    """{link: (A, A_R_link)} the constant bend (N5) of each single unsensed link (distal segment D in `only`,
    () = all) that the graph's lumped joint implies: d = bRs_A (l_A,D − l_A,up), l_A,up the lever of A's own
    proximal joint on A's sensor (the root: d = bRs_A l_A,D + b_pos_A with b_pos_A, A's sensor origin on A,
    the mean of b_j − bRs_A l_A,j over A's other joints j). `place`: the placements to use ({segment: (bRs, b_pos)});
    None: estimated from x's N-pose keyframes (the fixed lag passes its bootstrap's: its window holds no N-pose)."""
    from imugraph.graphs.body_output import estimate_placements
    place = estimate_placements(pb, x)[0] if place is None else place
    skel = pb.skel
    lev = {(seg, jj): i for i, (seg, jj, _) in enumerate(pb.levers)}
    out = {}
    for j, A, link, D in split_chains(pb, only):
        bRs_A, b_pos_A = place[A]
        up = next((jj for jj, jt in enumerate(pb.joints) if jt.child == A), None)
        l_D = np.asarray(x.atPoint3(bf.lever_key(lev[(A, j)])), float)
        if up is not None:
            d = bRs_A @ (l_D - x.atPoint3(bf.lever_key(lev[(A, up)])))
        else:                                   # the root: its sensor origin from its OTHER joints (not circular)
            other = [(jt.b_parent if jt.parent == A else jt.b_child) - bRs_A @ x.atPoint3(bf.lever_key(lev[(A, jj)]))
                     for jj, jt in enumerate(pb.joints) if A in (jt.parent, jt.child) and jj != j]
            d = bRs_A @ l_D + (np.mean(other, axis=0) if other else b_pos_A)
        o_link = np.asarray(skel.offsets[skel.index(link)], float)
        o_D = np.asarray(skel.offsets[skel.index(D)], float)
        out[link] = (A, _rot_between(o_D, d - o_link))                                                  # (N5)
    return out


def bootstrap_bend(pb_b, x_b, graph, opts) -> tuple[dict, dict | None]:
    """({link: (A, A_R_link)}, the pass's info) for the fixed lag (BodyOptions.lag_neck_from_bootstrap): the (N6)
    pass ((N8), (N9) as `opts` set them) on the bootstrap's batch problem pb_b, solved at x_b with `graph`, and the
    constant bend (N5) its levers imply. The bend is a constant of the model, so the bootstrap's value holds for
    the whole stream; the stream itself keeps x_b (its levers and anchors are not moved by this pass).
    ({}, None) when `opts` asks for no bend, for nominal-frame priors, or pb_b has no lumped joint."""
    if not opts.unsensed_bend or opts.lever_prior_frame == "nominal":
        return {}, None
    saved = pb_b.opts, list(pb_b.levers), pb_b.bend_values
    pb_b.opts = dataclasses.replace(opts, hinges=())
    try:
        x_n, info = lever_pass(pb_b, x_b, graph)                                                    # (N6), (N8), (N9)
        if info is None:
            return {}, None
        return solved_bend(pb_b, x_n), info                                                         # (N5)
    finally:
        pb_b.opts, pb_b.levers, pb_b.bend_values = saved


def apply_bend(bend: dict, q_seg: dict) -> dict:
    """{link: (N, 4) nR_link = nR_A · A_R_link} (N5) for a bend of `graph_bend`, given per-sample q_seg."""
    return {link: quat_mul(q_seg[A], np.broadcast_to(rotmat_to_quat(R), q_seg[A].shape))
            for link, (A, R) in bend.items()}


def link_orientations(pb, x, q_seg: dict) -> dict:
    """{link: (N, 4) nR_link = nR_A · A_R_link} (N5) for the links above BodyOptions.unsensed_bend's segments
    (() : {}), given the sensed segments' per-sample orientations q_seg."""
    if not pb.opts.unsensed_bend:
        return {}
    return apply_bend(solved_bend(pb, x), q_seg)


def solved_bend(pb, x) -> dict:
    """The constant bend (N5) of pb.opts.unsensed_bend's links at the solution `x`, read from the (N9)
    magnetometer-free levers when that pass stored them (pb.bend_values)."""
    return graph_bend(pb, x if pb.bend_values is None else pb.bend_values, tuple(pb.opts.unsensed_bend))
