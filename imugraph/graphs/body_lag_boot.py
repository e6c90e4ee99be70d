"""The fixed lag's bootstrap hand-over (helper L22): keyframe values, time stamps, the re-streamed overlap.

(L5) BodyOptions.lag_bootstrap_overlap_s: `overlap_start` — the bootstrap's keyframes of its last seconds are solved again
     by the stream (started at the bootstrap's estimate, `values_at`); measured: no gain (docs/results_issue4.md, session 22).
(L7) BodyOptions.lag_bootstrap_marginal: the bootstrap's own factors enter the smoother as its first update, from the
     bootstrap's estimate (`values_k0`, `values_at`), and `marginal_stamps` times the keys so that none leaves the window
     before it is recorded, then each leaves at its real time (the smoother marginalises it — a dense, correctly
     linearised prior instead of body_lag_boot.anchor's diagonal one); the N-pose keyframes are re-stamped and stay.
(C1) BodyOptions.lag_init_causal (helper B23): `causal_start` — the stream's problem from the bootstrap's rows only.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors import body as bf


def overlap_start(pb, k_first: int, overlap_s: float) -> int:
    """(L5) BodyOptions.lag_bootstrap_overlap_s: the first keyframe the stream solves again — the bootstrap's
    keyframes of its last overlap_s seconds (after its N-pose) are re-estimated by the smoother with the data that
    follow, instead of being output as the end of a batch that saw none (k_first: no overlap)."""
    if not overlap_s or k_first < 2:
        return k_first
    t_end = pb.kf_t[k_first - 1]
    k0 = max(int(np.sum(pb.kf <= pb.npose_idx[-1])), 1)      # never re-stream the N-pose
    ks = [k for k in range(k0, k_first) if t_end - pb.kf_t[k] < overlap_s]
    return ks[0] if ks else k_first


def values_at(pb, x: gtsam.Values, k: int) -> gtsam.Values:
    """Keyframe k's variables (and a bias segment's key it starts) from the bootstrap estimate x (L5)."""
    v = gtsam.Values()
    for s in range(len(pb.names)):
        v.insert(bf.pose_key(s, k), x.atPose3(bf.pose_key(s, k)))
        v.insert(bf.vel_key(s, k), x.atVector(bf.vel_key(s, k)))
        if pb.bkey(s, k) != pb.bkey(s, k - 1):
            v.insert(pb.bkey(s, k), x.atConstantBias(pb.bkey(s, k)))
    for j in range(len(pb.joints)):
        v.insert(bf.joint_key(j, k), x.atPoint3(bf.joint_key(j, k)))
    return v


def values_k0(pb, x: gtsam.Values) -> gtsam.Values:
    """Keyframe 0 and the global variables from the bootstrap estimate x (L7)."""
    v = gtsam.Values()
    for s in range(len(pb.names)):
        v.insert(bf.pose_key(s, 0), x.atPose3(bf.pose_key(s, 0)))
        v.insert(bf.vel_key(s, 0), x.atVector(bf.vel_key(s, 0)))
        v.insert(pb.bkey(s, 0), x.atConstantBias(pb.bkey(s, 0)))
    for j in range(len(pb.joints)):
        v.insert(bf.joint_key(j, 0), x.atPoint3(bf.joint_key(j, 0)))
    for i in range(len(pb.levers)):
        v.insert(bf.lever_key(i), x.atPoint3(bf.lever_key(i)))
    return v


def marginal_stamps(pb, ks: list[int], new: gtsam.Values, restamp: list[int], boot_keys: dict, first: bool,
                    keys_at, bias_stamps) -> dict[int, float]:
    """(L7) key → time stamp of a fixed-lag update: the first update (the bootstrap's keyframes) stamps every key with
    the current time so none leaves before it is recorded, and remembers their real times in `boot_keys`; the next
    update stamps them back to those (the smoother marginalises the ones older than the lag), then as usual: keyframe
    keys at their time, bias keys at their last use, `restamp` (globals, N-pose keyframes) at the current time.
    keys_at(pb, k), bias_stamps(pb, ks): body_incremental's keyframe keys and bias stamps."""
    now = float(pb.kf_t[ks[-1]])
    out = {} if first else dict(boot_keys)
    if not first:
        boot_keys.clear()
    for k in ks:
        for key in keys_at(pb, k):
            if new.exists(key):
                out[key] = now if first else float(pb.kf_t[k])
                if first:
                    boot_keys[key] = float(pb.kf_t[k])
    for key, tk in bias_stamps(pb, ks).items():
        out[key] = now if first else max(tk, out.get(key, -np.inf))
        if first:
            boot_keys[key] = tk
    out.update({key: now for key in restamp})
    return out


def anchor(pb, x: gtsam.Values, k: int, lever_sigmas: dict | None = None
            ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Priors on keyframe k's states and the global variables at their bootstrap estimate (a diagonal
    stand-in for the bootstrap's marginal: σ 0.01 rad / 0.01 m pose, 0.02 m/s velocity, bias σ 0.02 m/s²
    and 0.002 rad/s, lever arms 0.005 m; `lever_sigmas` {lever key: σ} overrides the last, body_lag_neck (L2))."""
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
        key = bf.lever_key(i)
        m_i = lever_m if key not in (lever_sigmas or {}) else gtsam.noiseModel.Isotropic.Sigma(3, lever_sigmas[key])
        g.add(gtsam.PriorFactorPoint3(key, x.atPoint3(key), m_i))
        v.insert(bf.lever_key(i), x.atPoint3(bf.lever_key(i)))
    return g, v


def bootstrap_rows(session, pb, opts, bootstrap_s: float) -> tuple[int, int]:
    """(m, n): the bootstrap's last keyframe index m and its row count n = kf[m] + 1 (body_incremental._bootstrap)."""
    rate = 1.0 / float(np.median(np.diff(session.t)))
    m = int(np.clip(round(bootstrap_s * rate / max(1, opts.keyframe_every)), 1, pb.K - 2))
    return m, int(pb.kf[m]) + 1


def causal_start(session, pb, opts, bootstrap_s: float | None):
    """(C1) BodyOptions.lag_init_causal (helper B23): the stream's problem from the rows its bootstrap has, only.

    Without it, build_problem on the whole session runs BodyOptions.init "motion"/"auto" (placement_motion (H1)–(H4))
    on init_motion_window_s (30 s) after the N-pose — rows the fixed lag has not received at its start — and those
    placements enter the stream through the k = 0 priors (heading of every sensor at pb.init) and the lever priors
    (B3) of its first update (lag_bootstrap_marginal (L7), or no bootstrap) and the neck's nominal lever (L4); the
    default anchor path reads none of them (benchmarks/b23_lag_causal.py, garbage from 2 updates after the bootstrap
    on: the filtered start bit-identical there; 29° / 67° with (L7) on the real walk / the turned simulation, 149° /
    160° with L22's lag_neck_stream + (L7) + (A2); bit-identical with this option in all of them). Here, with the bootstrap's rows [0, n) (`bootstrap_rows`):

        N-pose  = npose_samples(session[:n])          (detect_rest's calm-window median over those rows only)
        bRs_s   = with_motion_placements(session[:n]) (the bootstrap's own (H1)–(H4), its own "auto" switch)      (C1)

    and the whole-session problem is rebuilt with them as given placements (init "nominal", the N-pose as a window):
    the bootstrap and the stream then start from the same, causal placements. No bootstrap: nothing has arrived
    before the first update, so the nominal start. `pb` must come from build_problem(session, opts with init
    "nominal"). Returns (pb, opts for the bootstrap and the stream)."""
    from dataclasses import replace

    from imugraph.body.placement_motion import with_motion_placements
    from imugraph.graphs.body import build_problem
    from imugraph.graphs.body_model import npose_samples

    if bootstrap_s is None:
        return pb, replace(opts, init="nominal")
    _, n = bootstrap_rows(session, pb, opts, bootstrap_s)
    sub = replace(session, t=session.t[:n], sensors={k: v.slice(0, n) for k, v in session.sensors.items()})
    idx, method = npose_samples(sub, opts)
    opts_c, info = with_motion_placements(sub, opts, idx)                                                  # (C1)
    t = np.asarray(session.t, float)
    if set(opts_c.placements) == set(opts.placements) and np.array_equal(idx, pb.npose_idx):     # nothing switched: pb as is
        pb.init_motion = info
        return pb, replace(opts, init="nominal")
    opts_c = replace(opts_c, init="nominal", npose=(float(t[idx[0]]), float(t[idx[-1]])))
    pb_c = build_problem(session, opts_c)
    pb_c.npose_method, pb_c.init_motion = method, info
    return pb_c, opts_c
