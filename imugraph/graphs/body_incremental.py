"""Incremental body estimation on the batch solver's graph: iSAM2, or a fixed-lag smoother.

Keyframe by keyframe, the factors whose newest keyframe is k (`imugraph.graphs.body.factors_at`) go into
the solver with new variables predicted from keyframe k−1's estimate: every sensor's NavState propagated by
its preintegrated IMU (x_k = pim.predict(x_{k−1}, b̂)), joint centres J = nTs_P l̂_P.

- lag_s None: gtsam.ISAM2 over the whole session (global variables — biases, lever arms — stay in it).
- Bias segments (random walk, BodyOptions.bias_rw): a segment's bias key enters with the keyframe that starts
  the segment (predicted = the previous segment's estimate) and is stamped, at every update, with the time of
  the newest keyframe whose factors use it (`_bias_stamps`), so the fixed-lag smoother marginalises it only
  after its last ImuFactor; with bias_rw None the single bias is used at every keyframe and never leaves.
- lag_s given: gtsam.BatchFixedLagSmoother with that lag (LM, `lag_iterations` per update, QR: Cholesky
  threw IndeterminateLinearSystem at the first update); the global keys (biases, lever arms) and the last
  `keep_npose` N-pose keyframes are re-stamped with the current time at every update so they are never
  marginalised (bRs keeps improving as motion makes the relative headings observable).
  Measured on the 4-sensor chain (12 s, second half, worst joint): IncrementalFixedLagSmoother 31.6° (lag
  1 s) and 4.2° (lag 2 s), with Cholesky "key has no clique" (borglab/gtsam #1638); the batch smoother
  2.0° (lag 1 s, one update per keyframe, 3 iterations) — default, available as smoother="incremental".
- `bootstrap_s` (default "auto"): the first seconds — N-pose plus some motion, which is what makes the
  relative headings and hence bRs observable — are solved in batch; bRs and ψ are then held, keyframe states
  and globals continue from the bootstrap's last keyframe under diagonal priors (`_anchor`), and no N-pose
  keys need to stay in the window. "auto" ends it once every sensor has turned ≥ 1 rad and accelerated
  ≥ 2 m/s beyond the N-pose (imugraph.graphs.body_bootstrap, A1). After a bootstrap the linear solves use
  Cholesky (the anchors make them well posed; QR without one), with weak priors on every new keyframe
  variable (`_weak_priors`: without them 26 of 88 updates of the 17-IMU 60 s run below threw
  IndeterminateLinearSystem during the standing phases). gaittoolbox walk (7 MTw, 100 Hz, auto bootstrap to
  13.5 s, offset handling vs Vicon; batch 5.03°): lag 2 s 5.09–5.12° at 3.7–6.6× real time (QR: 1.9×),
  iSAM2 5.11° at 5.1× (relinearisation threshold 0.1; 0.01 and QR: 0.58×). Without a bootstrap the same
  lag-2 s smoother reached 13.1° at 0.63× (QR), and 3 LM iterations per update did not help (13.7°, 0.18×):
  bRs comes from an N-pose whose headings were not yet observable and is improved only through linearised
  marginals. benchmarks/body_speed.py (17 IMUs, 60 s walk at 60 Hz, auto bootstrap 16.4 s, lag 1 s,
  keyframes at 10 Hz, 5 per update, one LM iteration): Cholesky 4.3–11.5× real time on the streamed 43.6 s
  (the spread is the shared machine's load), worst joint 2.1–2.3° (QR: 1.29×, 2.48°; batch: 1.0–1.4°);
  iSAM2 1.8–2.65×, 2.1–2.2°, peak RSS 1.6 GB. A bootstrap without motion cannot fix bRs (8 s of standing:
  15° bRs errors).
- `update_every` keyframes per update (default 5): the cost of an update barely depends on how many new
  keyframes it brings, so fewer updates are cheaper; 17 IMUs, 20 s walk, keyframes at 5 Hz, lag 1 s, one
  LM iteration: 0.94× real time (benchmarks/body_speed.py).

- The unsensed neck: the stream keeps the ties (K2) (body_neck.single_pass_options); with
  BodyOptions.lag_neck_from_bootstrap (off by default) the bootstrap runs the (N6) pass and the output turns the
  neck by the constant bend (N5) read there (body_neck.bootstrap_bend), for the whole stream.

Output: the final estimate (iSAM2: its last full estimate; fixed lag: each keyframe's estimate as it leaves
the window, i.e. smoothed with lag_s) as a `BodyResult`, and in `info["filtered"]` the same built from the
estimate of each keyframe right after its own update (causal at keyframes; samples between keyframes are
interpolated as in the batch output, a latency of one keyframe interval). `info["update_s"]` holds the
wall time of every update.
"""

from __future__ import annotations

import time
from dataclasses import replace

import gtsam
import numpy as np

from imugraph.errors import SessionError
from imugraph.factors import body as bf
from imugraph.graphs.body import BodyProblem, build_problem, factors_at, optimize_with_mag_noise
from imugraph.graphs.body_bootstrap import motion_bootstrap_s
from imugraph.graphs import body_neck
from imugraph.graphs.body_model import BodyOptions
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.graphs.body_init import rz
from imugraph.graphs.body_output import (BodyResult, estimate_placements, fill_segments, forward_kinematics,
                                         make_result)


def _global_keys(pb: BodyProblem) -> list[int]:
    """Keys re-stamped at every fixed-lag update: the lever arms (bias keys: `_bias_stamps`)."""
    return [bf.lever_key(i) for i in range(len(pb.levers))]


def _bias_stamps(pb: BodyProblem, ks: list[int]) -> dict[int, float]:
    """Bias key → time of the newest keyframe among ks whose factors use it (ImuFactor from k−1, random-walk
    link into k's segment): a segment's bias leaves the fixed-lag window only after its last use."""
    out = {}
    for k in ks:
        for s in range(len(pb.names)):
            for key in {pb.bkey(s, k), pb.bkey(s, max(k - 1, 0))}:
                out[key] = max(out.get(key, -np.inf), float(pb.kf_t[k]))
    return out


def _keys_at(pb: BodyProblem, k: int) -> list[int]:
    out = []
    for s in range(len(pb.names)):
        out += [bf.pose_key(s, k), bf.vel_key(s, k)]
    return out + [bf.joint_key(j, k) for j in range(len(pb.joints))]


def _predict(pb: BodyProblem, est: gtsam.Values, k: int) -> gtsam.Values:
    """Initial values of keyframe k's variables from keyframe k−1's estimate (module docstring)."""
    v = gtsam.Values()
    poses = {}
    for s, name in enumerate(pb.names):
        state = gtsam.NavState(est.atPose3(bf.pose_key(s, k - 1)), est.atVector(bf.vel_key(s, k - 1)))
        b_prev = est.atConstantBias(pb.bkey(s, k - 1))
        nxt = pb.pims[name][k - 1].predict(state, b_prev)
        if pb.bkey(s, k) != pb.bkey(s, k - 1):            # a new bias segment starts: its random walk's mean
            v.insert(pb.bkey(s, k), b_prev)
        poses[name] = nxt.pose()
        v.insert(bf.pose_key(s, k), nxt.pose())
        v.insert(bf.vel_key(s, k), nxt.velocity())
    lever_index = {(seg, j): i for i, (seg, j, _) in enumerate(pb.levers)}
    for j, jt in enumerate(pb.joints):
        lev = est.atPoint3(bf.lever_key(lever_index[(jt.parent, j)]))
        v.insert(bf.joint_key(j, k), poses[jt.parent].transformFrom(lev))
    return v


def _initial_k0(pb: BodyProblem) -> gtsam.Values:
    """Keyframe 0 and the global variables from the batch initial values."""
    out = gtsam.Values()
    for s in range(len(pb.names)):
        out.insert(bf.pose_key(s, 0), pb.init.atPose3(bf.pose_key(s, 0)))
        out.insert(bf.vel_key(s, 0), pb.init.atVector(bf.vel_key(s, 0)))
        out.insert(pb.bkey(s, 0), pb.init.atConstantBias(pb.bkey(s, 0)))
    for j in range(len(pb.joints)):
        out.insert(bf.joint_key(j, 0), pb.init.atPoint3(bf.joint_key(j, 0)))
    for i in range(len(pb.levers)):
        out.insert(bf.lever_key(i), pb.init.atPoint3(bf.lever_key(i)))
    return out


def solve_body_incremental(session, opts: BodyOptions = BodyOptions(), lag_s: float | None = None,
                           relinearize_threshold: float | None = None, smoother: str = "batch",
                           lag_iterations: int = 1, keep_npose: int = 2, factorization: str | None = None,
                           update_every: int = 5, bootstrap_s: float | str | None = "auto") -> BodyResult:
    """iSAM2 (lag_s None) or fixed-lag smoothing over the body graph; see the module docstring.

    Args:
        session: BodySession; opts: the batch solver's options (same graph).
        lag_s: None for iSAM2 over everything, else the smoother lag in s.
        relinearize_threshold: iSAM2 relinearisation threshold (tangent-space step that triggers a
            relinearisation); None: 0.1 after a bootstrap (17 IMUs × 60 s at 60 Hz, auto bootstrap: 2.65× real
            time, worst joint 2.09°, peak RSS 1.65 GB; 0.01: 0.37×, 2.07°, 3.2 GB — benchmarks/body_speed.py
            set-up), 0.01 without one (the headings then move far from their first linearisation point:
            tests/test_body_graph.py's chain, 2.3° with 0.1).
        smoother: "batch" (BatchFixedLagSmoother, LM with `lag_iterations` per update) or "incremental"
            (IncrementalFixedLagSmoother, iSAM2 with `factorization`).
        lag_iterations: LM iterations per update (batch smoother), iSAM2 update() calls per update (iSAM2).
        keep_npose: the last N-pose keyframes kept in the window (re-stamped) so bRs keeps improving.
        factorization: "QR" or "CHOLESKY" (iSAM2, and the batch smoother's MULTIFRONTAL_ solver); None:
            Cholesky after a bootstrap (its anchor priors make every update well posed; gaittoolbox walk,
            lag 2 s: 6.8× real time vs 1.9× with QR, same accuracy; iSAM2 2.4× vs 0.58×), QR without.
        update_every: keyframes per solver update (>1: the newest keyframes of an update are estimated
            with up to update_every − 1 keyframes of look-ahead; fewer, cheaper updates).
        bootstrap_s: batch-solve the first bootstrap_s seconds (N-pose and some motion), fix bRs and ψ from
            it, then continue incrementally from its last keyframe (see `_anchor`); its wall time is in
            info["bootstrap"], not in update_s. "auto" (default): until every sensor has turned and
            accelerated enough (imugraph.graphs.body_bootstrap, A1). None: incremental from the first sample.
    """
    t_start = time.perf_counter()
    neck_opts = opts if opts.lag_neck_from_bootstrap and bootstrap_s is not None else None
    opts = body_neck.single_pass_options(opts)          # no (N6) pass in the stream: ties (K2), or the bootstrap's bend
    pb = build_problem(session, opts)
    kf_t = pb.kf_t
    span = float(np.median(np.diff(kf_t))) * max(1, int(update_every)) if pb.K > 1 else 0.0
    if lag_s is not None and not lag_s >= span:
        raise SessionError(session.source, "lag_s", f"{lag_s} s",
                           f"≥ the {span:.2f} s of keyframes added per update (update_every × keyframe interval)")
    glob = _global_keys(pb)
    n_npose = int(np.sum(pb.kf <= pb.npose_idx[-1]))
    npose_keys = [key for k in range(max(0, n_npose - keep_npose), n_npose) for key in _keys_at(pb, k)]
    records = []                                  # per keyframe: (sensor nRs (n,3,3), p, v of root, bRs, ψ)
    lagged: dict = {}                             # fixed lag: the record of each keyframe as it leaves the window
    update_s, failures, first_failure = [], 0, None
    est, fixed_place, k_first, boot, bend = None, None, 0, {}, {}
    anchor, anchor_vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    auto = {}
    if isinstance(bootstrap_s, str):
        if bootstrap_s != "auto":
            raise SessionError(session.source, "bootstrap_s", repr(bootstrap_s), '"auto", seconds or None')
        bootstrap_s, auto = motion_bootstrap_s(session, pb)
    if factorization is None:
        factorization = "QR" if bootstrap_s is None else "CHOLESKY"
    if relinearize_threshold is None:
        relinearize_threshold = 0.01 if bootstrap_s is None else 0.1
    solver = _make_solver(lag_s, smoother, factorization, relinearize_threshold, lag_iterations)
    regularize = factorization.upper() == "CHOLESKY"
    if bootstrap_s is not None:
        k_first, x_b, fixed_place, boot, bend = _bootstrap(session, pb, opts, bootstrap_s, neck_opts)
        boot.update(auto)
        for k in range(k_first):
            records.append(_record(pb, x_b, k, fixed_place))
            lagged[k] = records[-1]
        anchor, anchor_vals = _anchor(pb, x_b, k_first - 1)
        npose_keys = []
    M = max(1, int(update_every))
    for k_end in range(k_first, pb.K, M):
        ks = list(range(k_end, min(k_end + M, pb.K)))
        graph, new = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k_end == k_first and k_first > 0:      # bootstrap: its last keyframe and globals, anchored
            graph.push_back(anchor)
            new.insert(anchor_vals)
            ks_stamp = [k_first - 1] + ks
        else:
            ks_stamp = ks
        cur = gtsam.Values(new) if est is None else gtsam.Values(est)
        for k in ks:                              # predictions chain through the batch's own new keyframes
            graph.push_back(factors_at(pb, k))
            v = _initial_k0(pb) if k == 0 else _predict(pb, cur, k)
            if regularize:
                graph.push_back(_weak_priors(v))
            new.insert(v)
            cur.insert(v)
        t0 = time.perf_counter()
        try:
            if lag_s is not None:
                stamps = gtsam.FixedLagSmootherKeyTimestampMap()
                restamp = glob + [key for key in npose_keys if est is not None and est.exists(key)]
                for k in ks_stamp:
                    for key in _keys_at(pb, k):
                        if new.exists(key):
                            stamps.insert((key, float(kf_t[k])))
                for key in restamp:
                    stamps.insert((key, float(kf_t[ks[-1]])))
                for key, tk in _bias_stamps(pb, ks).items():
                    stamps.insert((key, tk))
                solver.update(graph, new, stamps)
            else:
                solver.update(graph, new)
                for _ in range(max(0, lag_iterations - 1)):     # extra iSAM2 relinearisation steps
                    solver.update()
            est = solver.calculateEstimate()
        except RuntimeError as exc:               # counted, never raised after the start (as the stream does)
            failures += 1
            if est is None:
                raise
            first_failure = first_failure or f"keyframe {ks[0]}: {str(exc)[:300]}"
            est = cur
        update_s.append(time.perf_counter() - t0)
        place = fixed_place if fixed_place is not None else estimate_placements(pb, est)
        for k in ks:
            records.append(_record(pb, est, k, place))
        if lag_s is not None:                     # keyframes still in the window: latest (lag-smoothed) estimate
            k_old = ks[-1]
            while k_old >= 0 and kf_t[ks[-1]] - kf_t[k_old] <= lag_s + 1e-9:
                if est.exists(bf.pose_key(0, k_old)):
                    lagged[k_old] = _record(pb, est, k_old, place)
                k_old -= 1
    total = time.perf_counter() - t_start
    dur = float(session.t[-1] - (session.t[pb.kf[k_first - 1]] if k_first > 0 else session.t[0]))  # streamed
    info = {"mode": "isam2" if lag_s is None else f"fixed_lag_{lag_s}s", "keyframes": pb.K,
            "update_s": np.asarray(update_s), "total_s": total, "failed_updates": failures,
            "first_failure": first_failure,
            "realtime_factor": dur / max(float(np.sum(update_s)), 1e-12), "npose": pb.npose_method,
            "bootstrap": boot}
    if pb.mag_sigmas:
        info["mag_sigmas"] = dict(pb.mag_sigmas)  # (B5') the σ the stream's magnetometer factors used
    info["filtered"] = filtered_result(pb, records, bend)
    if lag_s is None and fixed_place is None:         # no bootstrap: lag_neck_from_bootstrap has nothing to read
        return make_result(pb, est, info)
    if lag_s is None:                             # iSAM2 after a bootstrap: its final estimate, bRs held
        lagged.update({k: _record(pb, est, k, fixed_place) for k in range(k_first, pb.K)})
    res = filtered_result(pb, [lagged[k] for k in range(pb.K)], bend)
    return BodyResult(res.t, res.names, res.n_quat, res.n_pos, res.placements, info)


def _weak_priors(v: gtsam.Values) -> gtsam.NonlinearFactorGraph:
    """Priors σ 1 rad / 10 m / 10 m/s at the predicted values of new keyframe variables: a regulariser
    (information 1–0.01 against ≥ 10⁵ from the IMU and joint factors) that keeps Cholesky's eliminations
    positive definite while the body stands still."""
    g = gtsam.NonlinearFactorGraph()
    pose_m = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 1.0), np.full(3, 10.0)])
    vec_m = gtsam.noiseModel.Isotropic.Sigma(3, 10.0)
    for key in v.keys():
        ch = chr(gtsam.Symbol(key).chr())
        if ch == "x":
            g.add(gtsam.PriorFactorPose3(key, v.atPose3(key), pose_m))
        elif ch == "v":
            g.add(gtsam.PriorFactorVector(key, v.atVector(key), vec_m))
        elif ch == "j":
            g.add(gtsam.PriorFactorPoint3(key, v.atPoint3(key), vec_m))
    return g


def _make_solver(lag_s, smoother: str, factorization: str, relinearize_threshold: float, lag_iterations: int):
    """gtsam.ISAM2 (lag_s None), BatchFixedLagSmoother ("batch") or IncrementalFixedLagSmoother."""
    if lag_s is None or smoother != "batch":
        prm = gtsam.ISAM2Params()
        prm.setRelinearizeThreshold(relinearize_threshold)
        prm.relinearizeSkip = 1
        prm.setFactorization(factorization)   # QR without a bootstrap: Cholesky threw IndeterminateLinearSystem
        return gtsam.ISAM2(prm) if lag_s is None else gtsam.IncrementalFixedLagSmoother(float(lag_s), prm)
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(lag_iterations)
    lm.setLinearSolverType(f"MULTIFRONTAL_{factorization}")
    return gtsam.BatchFixedLagSmoother(float(lag_s), lm)


def _bootstrap(session, pb: BodyProblem, opts: BodyOptions, bootstrap_s: float, neck_opts: BodyOptions | None = None):
    """Batch solve of the first keyframes: (first keyframe index to stream, estimate, (bRs…, ψ), info, bend);
    bend: {} or, with `neck_opts` (BodyOptions.lag_neck_from_bootstrap), the neck's constant bend (N5) from the
    (N6) pass on this batch graph (body_neck.bootstrap_bend; the estimate returned stays the first pass's)."""
    t0 = time.perf_counter()
    rate = 1.0 / float(np.median(np.diff(session.t)))
    m = int(np.clip(round(bootstrap_s * rate / max(1, opts.keyframe_every)), 1, pb.K - 2))
    n = int(pb.kf[m]) + 1                                   # the sub-problem's last keyframe is pb.kf[m]
    sub = replace(session, t=session.t[:n], sensors={k: v.slice(0, n) for k, v in session.sensors.items()})
    pb_b = build_problem(sub, replace(opts, hinges=()))
    x_b, passes, graph = optimize_with_mag_noise(pb_b)
    pb.mag_dirs, pb.mag_sigmas = pb_b.mag_dirs, pb_b.mag_sigmas    # (B5') carried into the stream
    place = estimate_placements(pb_b, x_b)
    bend, neck_info = body_neck.bootstrap_bend(pb_b, x_b, graph, neck_opts) if neck_opts is not None else ({}, None)
    info = {"seconds": time.perf_counter() - t0, "keyframes": m + 1,
            "iterations": sum(p["iterations"] for p in passes), "psi_deg": float(np.rad2deg(place[1]))}
    if neck_info is not None:
        info["neck_pass_iterations"] = neck_info["iterations"]
    return m + 1, x_b, place, info, bend


def _anchor(pb: BodyProblem, x: gtsam.Values, k: int) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Priors on keyframe k's states and the global variables at their bootstrap estimate (a diagonal
    stand-in for the bootstrap's marginal: σ 0.01 rad / 0.01 m pose, 0.02 m/s velocity, bias σ 0.02 m/s²
    and 0.002 rad/s, lever arms 0.005 m)."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pose_m = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 0.01))
    vel_m = gtsam.noiseModel.Isotropic.Sigma(3, 0.02)
    bias_m = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 0.02), np.full(3, 0.002)])
    lever_m = gtsam.noiseModel.Isotropic.Sigma(3, 0.005)
    for s in range(len(pb.names)):
        T, vel, b = x.atPose3(bf.pose_key(s, k)), x.atVector(bf.vel_key(s, k)), x.atConstantBias(pb.bkey(s, k))
        g.add(gtsam.PriorFactorPose3(bf.pose_key(s, k), T, pose_m))
        g.add(gtsam.PriorFactorVector(bf.vel_key(s, k), vel, vel_m))
        g.add(gtsam.PriorFactorConstantBias(pb.bkey(s, k), b, bias_m))   # same segments in the prefix problem
        v.insert(bf.pose_key(s, k), T)
        v.insert(bf.vel_key(s, k), vel)
        v.insert(pb.bkey(s, k), b)
    for i in range(len(pb.levers)):
        g.add(gtsam.PriorFactorPoint3(bf.lever_key(i), x.atPoint3(bf.lever_key(i)), lever_m))
        v.insert(bf.lever_key(i), x.atPoint3(bf.lever_key(i)))
    return g, v


def _record(pb: BodyProblem, est: gtsam.Values, k: int, place_psi: tuple) -> dict:
    """What the filter knows right after keyframe k's update: keyframe k's sensor states, the biases and the
    sensor-to-segment rotations from the CURRENT estimate of the N-pose (heading becomes observable only
    once the subject moves, so these improve over time)."""
    place, psi = place_psi
    S = len(pb.names)
    return {"nRs": np.stack([est.atPose3(bf.pose_key(s, k)).rotation().matrix() for s in range(S)]),
            "p": est.atPose3(bf.pose_key(0, k)).translation(), "v": est.atVector(bf.vel_key(0, k)),
            "b_gyr": np.stack([est.atConstantBias(pb.bkey(s, k)).gyroscope() for s in range(S)]),
            "place": place, "psi": psi}


def filtered_result(pb: BodyProblem, records: list, bend: dict | None = None) -> BodyResult:
    """Causal per-sample output: from keyframe k's filtered state, the gyro integrated forward to the samples
    before keyframe k+1 (R_{i+1} = R_i Exp((ω_i − b̂_k) dt_i)), segment rotations nRb = Rz(ψ₀ − ψ_k) nRs bRs_kᵀ
    with keyframe k's sensor-to-segment rotations, root sensor position p_k + v_k τ; `bend` (the bootstrap's
    body_neck.bootstrap_bend): those links turn with their upper neighbour (N5), the others keep the ties (K2)."""
    t = np.asarray(pb.session.t, float)
    N, K = t.size, len(records)
    kf = pb.kf[:K]
    L = np.diff(np.append(kf, N))                       # samples owned by each keyframe
    nRg = np.stack([rz(np.deg2rad(pb.opts.npose_heading_deg) - r["psi"]) for r in records])     # (K,3,3)
    q_seg = {}
    for s, name in enumerate(pb.names):
        sess = pb.session.sensors[name]
        R = np.stack([r["nRs"][s] for r in records])
        b = np.stack([r["b_gyr"][s] for r in records])
        bRs = np.stack([r["place"][name][0] for r in records])
        G = nRg                                          # (K,3,3) graph → output rotation per keyframe
        nRb = np.empty((N, 3, 3))
        for m in range(int(L.max())):
            ok = m < L
            i = kf[ok] + m
            if m > 0:
                R[ok] = R[ok] @ expmap((sess.gyr[i - 1] - b[ok]) * sess.dt[i - 1][:, None])
            nRb[i] = G[ok] @ R[ok] @ np.swapaxes(bRs[ok], 1, 2)
            if s == 0:
                if m == 0:
                    root = np.empty((N, 3))
                bRs0 = bRs[ok]
                b_pos0 = np.stack([records[k]["place"][name][1] for k in np.flatnonzero(ok)])
                p_s = np.stack([records[k]["p"] + records[k]["v"] * (t[kf[k] + m] - t[kf[k]]) for k in np.flatnonzero(ok)])
                o = p_s + np.einsum("kij,kj->ki", R[ok], np.einsum("kji,kj->ki", bRs0, -b_pos0))
                root[i] = np.einsum("kij,kj->ki", G[ok], o)
        q_seg[name] = rotmat_to_quat(nRb)
    q_seg.update(body_neck.apply_bend(bend or {}, q_seg))          # nR_u = nR_A · A_R_u (N5)
    n_quat = fill_segments(pb.skel, q_seg)
    n_pos = forward_kinematics(pb.skel, n_quat, root)
    return BodyResult(t, tuple(pb.skel.names), n_quat, n_pos,
                      {n: {"bRs": records[-1]["place"][n][0], "b_pos": records[-1]["place"][n][1]} for n in pb.names},
                      {"mode": "filtered", "npose_heading_deg": [float(np.rad2deg(r["psi"])) for r in records]})
