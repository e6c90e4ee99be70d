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
  and globals continue from the bootstrap's last keyframe under diagonal priors (`body_lag_boot.anchor`), and no N-pose
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
- Helper L22 (all off by default): `lag_neck_stream` — the stream's own levers carry the neck's bend, read per
  keyframe as it leaves the window (imugraph.graphs.body_lag_neck (L1)–(L4)); `lag_bootstrap_marginal` (L7) — the
  bootstrap's factors enter the smoother as its first update (from the bootstrap's estimate), the last N-pose
  keyframes stay in the window and bRs, ψ are re-estimated at every update instead of held; `lag_bootstrap_settle_deg`
  (A2) — the auto bootstrap extended until bRs settles (imugraph.graphs.body_lag_settle); `lag_bootstrap_scale` (L6)
  — (A1)'s thresholds scaled; `lag_bootstrap_overlap_s` (L5) — the bootstrap's last seconds re-streamed (no gain
  measured). Numbers: docs/results_issue4.md, "Session 22, helper L22".
- Helper B23 (off by default): `lag_init_causal` (body_lag_boot.causal_start (C1)) — the problem the stream uses takes
  its N-pose and its init "motion"/"auto" placements from the bootstrap's rows, not from 30 s of the whole session
  (which (L7)'s first update reads through its k = 0 and lever priors). docs/results_issue4.md, "Session 23, helper B23".

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
from imugraph.graphs.body_bootstrap import MIN_DV, MIN_TURN_RAD, motion_bootstrap_s
from imugraph.graphs.body_lag_settle import settled_bootstrap_s
from imugraph.graphs import body_lag_boot, body_lag_neck, body_neck
from imugraph.graphs.body_model import BodyOptions
from imugraph.graphs.body_lag_output import _record, filtered_result
from imugraph.graphs.body_output import BodyResult, estimate_placements, make_result


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
            it, then continue incrementally from its last keyframe (see `body_lag_boot.anchor`); its wall time is in
            info["bootstrap"], not in update_s. "auto" (default): until every sensor has turned and
            accelerated enough (imugraph.graphs.body_bootstrap, A1). None: incremental from the first sample.
    """
    t_start = time.perf_counter()
    neck_opts = opts if opts.lag_neck_from_bootstrap and bootstrap_s is not None else None
    full_opts = opts                                    # lag_neck_stream (L1)–(L4) reads unsensed_bend from these
    stream_neck = body_lag_neck.wanted(opts, bootstrap_s)
    opts = body_neck.single_pass_options(opts)          # no (N6) pass in the stream: ties (K2), or the bootstrap's bend
    causal = bool(opts.lag_init_causal) and opts.init != "nominal"           # (C1) body_lag_boot.causal_start
    pb = build_problem(session, replace(opts, init="nominal") if causal else opts)
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
    est, fixed_place, k_first, k_stream, boot, bend = None, None, 0, 0, {}, {}
    marginal = bool(full_opts.lag_bootstrap_marginal and lag_s is not None and bootstrap_s is not None)     # (L7)
    lever_delta = None
    anchor, anchor_vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    auto = {}
    if isinstance(bootstrap_s, str):
        if bootstrap_s != "auto":
            raise SessionError(session.source, "bootstrap_s", repr(bootstrap_s), '"auto", seconds or None')
        scale = float(opts.lag_bootstrap_scale)           # (L6) the (A1) thresholds × scale
        bootstrap_s, auto = motion_bootstrap_s(session, pb, MIN_TURN_RAD * scale, MIN_DV * scale)
        if full_opts.lag_bootstrap_settle_deg is not None:                                      # (A2)
            bootstrap_s, settle = settled_bootstrap_s(
                lambda t: _bootstrap(session, pb, opts, t)[2][0], bootstrap_s, float(session.t[-1] - session.t[0]),
                full_opts.lag_bootstrap_settle_deg, full_opts.lag_bootstrap_settle_step_s)
            auto = dict(auto, bootstrap_s=bootstrap_s, **settle)
    if causal:                                          # (C1) placements and N-pose from the bootstrap's rows
        pb, opts = body_lag_boot.causal_start(session, pb, opts, bootstrap_s)
    if factorization is None:
        factorization = "QR" if bootstrap_s is None else "CHOLESKY"
    if relinearize_threshold is None:
        relinearize_threshold = 0.01 if bootstrap_s is None else 0.1
    solver = _make_solver(lag_s, smoother, factorization, relinearize_threshold, lag_iterations)
    regularize = factorization.upper() == "CHOLESKY"
    if bootstrap_s is not None:
        k_first, x_b, fixed_place, boot, bend = _bootstrap(session, pb, opts, bootstrap_s, neck_opts,
                                                           full_opts if stream_neck else None)
        boot.update(auto)
        lever_delta = boot.pop("lever_delta", None)                                              # (L8)
        k_stream = 0 if marginal else body_lag_boot.overlap_start(pb, k_first, full_opts.lag_bootstrap_overlap_s)      # (L5)
        if marginal:                                  # (L7) the bootstrap's factors enter the smoother itself
            fixed_place = None
            if stream_neck and boot.get("levers") is not None:
                pb.levers = boot.pop("levers")        # (N6)'s lever priors, as the bootstrap's pass had them
        for k in range(k_first if not marginal else 0):
            lagged[k] = _record(pb, x_b, k, fixed_place, bend if stream_neck else None)
            if k < k_stream:
                records.append(lagged[k])
        neck_sigma = {}
        if stream_neck and full_opts.lag_neck_anchor_sigma_m is not None:                       # (L2)
            neck_sigma = {key: full_opts.lag_neck_anchor_sigma_m for key in body_lag_neck.neck_lever_keys(pb, full_opts)}
        if not marginal:
            anchor, anchor_vals = body_lag_boot.anchor(pb, x_b, k_stream - 1, neck_sigma)
        if stream_neck:
            bend = {}                                   # per keyframe from here on (records' "bend", (L4))
        npose_keys = npose_keys if marginal else []
    M = max(1, int(update_every))
    chunks = [list(range(k, min(k + M, pb.K))) for k in range(k_first if marginal else k_stream, pb.K, M)]
    if marginal:
        chunks.insert(0, list(range(k_first)))
    boot_keys: dict = {}                          # (L7) first update's keys → their real time, re-stamped next update
    for ks in chunks:
        k_end = ks[0]
        graph, new = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k_end == k_stream and k_first > 0 and not marginal:     # bootstrap: its last keyframe, globals, anchored
            graph.push_back(anchor)
            new.insert(anchor_vals)
            ks_stamp = [k_stream - 1] + ks
        else:
            ks_stamp = ks
        cur = gtsam.Values(new) if est is None else gtsam.Values(est)
        for k in ks:                              # predictions chain through the batch's own new keyframes
            fk = factors_at(pb, k)
            if stream_neck:
                body_lag_neck.stream_factors(pb, fk, full_opts)                                 # (L3)
            graph.push_back(fk)
            if k == 0:
                v = _initial_k0(pb) if not marginal else body_lag_boot.values_k0(pb, x_b)
            else:                                 # (L5) the bootstrap's own keyframes start at its estimate
                v = _predict(pb, cur, k) if k >= k_first else body_lag_boot.values_at(pb, x_b, k)
            if regularize:
                graph.push_back(_weak_priors(v))
            new.insert(v)
            cur.insert(v)
        t0 = time.perf_counter()
        try:
            if lag_s is not None:
                stamps = gtsam.FixedLagSmootherKeyTimestampMap()
                restamp = glob + [key for key in npose_keys if est is not None and est.exists(key)]
                if marginal:                      # (L7)
                    restamp = glob + [key for key in npose_keys if est is None or est.exists(key)]
                    for key, tk in body_lag_boot.marginal_stamps(pb, ks, new, restamp, boot_keys, est is None,
                                                                  _keys_at, _bias_stamps).items():
                        stamps.insert((key, tk))
                else:
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
        bend_now = body_lag_neck.stream_bend(pb, est, place[0], full_opts, lever_delta) if stream_neck else None  # (L4)
        for k in ks:
            records.append(_record(pb, est, k, place, bend_now))
        if marginal and len(records) == len(ks):  # (L7) the bootstrap's keyframes, after their one joint update
            lagged.update({k: records[k] for k in ks})
        if lag_s is not None:                     # keyframes still in the window: latest (lag-smoothed) estimate
            k_old = ks[-1]
            while k_old >= 0 and kf_t[ks[-1]] - kf_t[k_old] <= lag_s + 1e-9:
                if est.exists(bf.pose_key(0, k_old)):
                    lagged[k_old] = _record(pb, est, k_old, place, bend_now)
                k_old -= 1
    total = time.perf_counter() - t_start
    dur = float(session.t[-1] - (session.t[pb.kf[k_stream - 1]] if k_stream > 0 else session.t[0]))  # streamed
    info = {"mode": "isam2" if lag_s is None else f"fixed_lag_{lag_s}s", "keyframes": pb.K,
            "update_s": np.asarray(update_s), "total_s": total, "failed_updates": failures,
            "first_failure": first_failure,
            "realtime_factor": dur / max(float(np.sum(update_s)), 1e-12), "npose": pb.npose_method,
            "bootstrap": boot}
    if pb.mag_sigmas:
        info["mag_sigmas"] = dict(pb.mag_sigmas)  # (B5') the σ the stream's magnetometer factors used
    if causal and pb.init_motion is not None:    # (C1): (H3)/(H4) on the bootstrap's rows (mocap_info.json)
        info["init_motion"] = pb.init_motion
    info["filtered"] = filtered_result(pb, records, bend)
    if lag_s is None and fixed_place is None:         # no bootstrap: lag_neck_from_bootstrap has nothing to read
        return make_result(pb, est, info)
    if lag_s is None:                             # iSAM2 after a bootstrap: its final estimate, bRs held
        bend_end = body_lag_neck.stream_bend(pb, est, fixed_place[0], full_opts, lever_delta) if stream_neck else None
        lagged.update({k: _record(pb, est, k, fixed_place, bend_end) for k in range(k_stream, pb.K)})
    info["lag_records"] = [lagged[k] for k in range(pb.K)]     # per keyframe as output (benchmarks/l22_lag_diag.py)
    res = filtered_result(pb, info["lag_records"], bend)
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


def _bootstrap(session, pb: BodyProblem, opts: BodyOptions, bootstrap_s: float, neck_opts: BodyOptions | None = None,
               stream_opts: BodyOptions | None = None):
    """Batch solve of the first keyframes: (first keyframe index to stream, estimate, (bRs…, ψ), info, bend);
    bend: {} or, with `neck_opts` (BodyOptions.lag_neck_from_bootstrap), the neck's constant bend (N5) from the
    (N6) pass on this batch graph (body_neck.bootstrap_bend; the estimate returned stays the first pass's).
    `stream_opts` (BodyOptions.lag_neck_stream): the estimate returned, its placements and the bend are the (N6)
    pass's (body_lag_neck (L1)), the stream continues from them."""
    t0 = time.perf_counter()
    m, n = body_lag_boot.bootstrap_rows(session, pb, opts, bootstrap_s)     # the sub-problem's last keyframe is pb.kf[m]
    sub = replace(session, t=session.t[:n], sensors={k: v.slice(0, n) for k, v in session.sensors.items()})
    pb_b = build_problem(sub, replace(opts, hinges=()))
    x_b, passes, graph = optimize_with_mag_noise(pb_b)
    pb.mag_dirs, pb.mag_sigmas = pb_b.mag_dirs, pb_b.mag_sigmas    # (B5') carried into the stream
    if stream_opts is not None:                                                                   # (L1)
        x_b, bend, neck_info = body_lag_neck.bootstrap_pass(pb_b, x_b, graph, stream_opts)
    place = estimate_placements(pb_b, x_b)
    if stream_opts is None:
        bend, neck_info = body_neck.bootstrap_bend(pb_b, x_b, graph, neck_opts) if neck_opts is not None else ({}, None)
    info = {"seconds": time.perf_counter() - t0, "keyframes": m + 1, "span_s": float(sub.t[-1] - sub.t[0]),
            "iterations": sum(p["iterations"] for p in passes), "psi_deg": float(np.rad2deg(place[1]))}
    if neck_info is not None:
        info["neck_pass_iterations"] = neck_info["iterations"]
        for key in ("levers", "lever_delta"):
            if key in neck_info:
                info[key] = neck_info[key]
    return m + 1, x_b, place, info, bend
