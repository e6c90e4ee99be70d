"""Chunked warm start of the body graph's batch LM (docs/diagnose_body.md, "Session 22, helper D22").

Why: the base fit's LM starts from gyro-integrated orientations and joint-chained positions (root at the
origin, graphs/body_init); their error grows with time, and so did the LM iteration count on the real walk
(9 iterations for its first 12.5 s, 18 for 25 s; docs §5): per iteration the cost is linear in the length
(sparse elimination along time), so the iteration count made the fit super-linear.

What: the SAME graph and optimum (the user's model is unchanged), only a better starting point, built in
overlapping time chunks of `chunk_s` seconds, each solved by the same LM on its own subgraph:

    chunk c = keyframes [a_c, b_c],  a_{c+1} = b_c − overlap                                        (C1)
    subgraph_c = {factors whose time-indexed keys (x, v, j: keyframe k; for a bias random-walk link, the
                  first keyframes of its two segments) all lie in [a_c, b_c]} ∪ {factors on the levers only (their priors)}
                 ∪ (c > 0) {priors at a_c on every sensor's pose, velocity and bias from chunk c−1's
                  solution (σ `BOUNDARY_SIGMA`): they carry the gauge and the past of the chunk}           (C2)
    start of chunk c > 0 beyond b_{c−1}: per sensor s the initial values corrected by the previous
        solution at its last keyframe b = b_{c−1}:
        R_k ← Δ_s R⁰_k,  Δ_s = R̂_b (R⁰_b)ᵀ;   p_k ← p̂_b + Δ_s (p⁰_k − p⁰_b);   v_k ← Δ_s v⁰_k;
        biases ← b̂_b;   joint centres ← p̂_P + R̂_P l̂ of the parent                                   (C3)

then the full LM from the stitched values (C4). Every chunk costs O(chunk length) and its iteration count is
bounded by the chunk's own drift, so the warm start is linear in the length; the final full LM converges in
a few iterations (measured: docs). Nothing of the model is lost: (C2)'s priors and per-chunk levers exist only
for the start; the final solve is the full graph. `chunk_s` None: the cold start (the default).
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors import body as bf

BOUNDARY_SIGMA = {"rot": 1e-3, "pos": 1e-3, "vel": 1e-3, "bias": 1e-3}    # (C2): rad, m, m/s, bias units
OVERLAP_S = 2.0                                                          # (C1) seconds of overlap


def _key_info(key: int) -> tuple[str, int, int]:
    sym = gtsam.Symbol(key)
    owner, k = divmod(int(sym.index()), bf._STRIDE)
    return chr(sym.chr()), owner, k


def factor_spans(pb, graph) -> np.ndarray:
    """(F, 2) first and last keyframe each factor touches; (−1, −1) for factors on global keys only."""
    seg = pb.bias_seg if pb.bias_seg is not None else np.zeros(pb.K, int)
    seg_first = {int(m): int(np.flatnonzero(seg == m)[0]) for m in np.unique(seg)}
    spans = np.full((graph.size(), 2), -1, int)
    for i in range(graph.size()):
        f = graph.at(i)
        if f is None:
            spans[i] = (-2, -2)                      # an emptied slot: in no chunk
            continue
        lo, hi = None, None
        info = [_key_info(key) for key in f.keys()]
        timed = any(c in ("x", "v", "j") for c, _, _ in info)
        for c, _, k in info:
            if c in ("x", "v", "j"):
                a, b = k, k
            elif c == "b" and not timed:          # a bias walk link: the first keyframes of its segments
                a = b = seg_first.get(k, 0)
            else:                                 # levers; a bias beside poses (ImuFactor): by its poses
                continue
            lo = a if lo is None else min(lo, a)
            hi = b if hi is None else max(hi, b)
        if lo is not None:
            spans[i] = (lo, hi)
    return spans


def _get(x: gtsam.Values, key: int):
    c = chr(gtsam.Symbol(key).chr())
    if c == "x":
        return x.atPose3(key)
    if c == "v":
        return np.asarray(x.atVector(key), float)
    if c == "b":
        return x.atConstantBias(key)
    return np.asarray(x.atPoint3(key), float)


def _boundary_priors(pb, x: gtsam.Values, k: int) -> gtsam.NonlinearFactorGraph:
    """(C2) at keyframe k from the current solution x."""
    g = gtsam.NonlinearFactorGraph()
    sp = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, BOUNDARY_SIGMA["rot"]), np.full(3, BOUNDARY_SIGMA["pos"])])
    sv = gtsam.noiseModel.Isotropic.Sigma(3, BOUNDARY_SIGMA["vel"])
    sb = gtsam.noiseModel.Isotropic.Sigma(6, BOUNDARY_SIGMA["bias"])
    for s in range(len(pb.names)):
        g.add(gtsam.PriorFactorPose3(bf.pose_key(s, k), x.atPose3(bf.pose_key(s, k)), sp))
        g.add(gtsam.PriorFactorVector(bf.vel_key(s, k), np.asarray(x.atVector(bf.vel_key(s, k)), float), sv))
        g.add(gtsam.PriorFactorConstantBias(pb.bkey(s, k), x.atConstantBias(pb.bkey(s, k)), sb))
    return g


def _propagate(pb, x: gtsam.Values, b: int, k_end: int) -> None:
    """(C3): initial values of keyframes b+1 … k_end corrected by the solution at keyframe b (in place)."""
    init = pb.init
    lever_index = {(seg, j): i for i, (seg, j, _) in enumerate(pb.levers)}
    for s in range(len(pb.names)):
        T_b, T0_b = x.atPose3(bf.pose_key(s, b)), init.atPose3(bf.pose_key(s, b))
        D = T_b.rotation().matrix() @ T0_b.rotation().matrix().T
        p_b, p0_b = np.asarray(T_b.translation(), float), np.asarray(T0_b.translation(), float)
        bias = x.atConstantBias(pb.bkey(s, b))
        for k in range(b + 1, k_end + 1):
            T0 = init.atPose3(bf.pose_key(s, k))
            R = D @ T0.rotation().matrix()
            x.update(bf.pose_key(s, k), gtsam.Pose3(gtsam.Rot3(R), p_b + D @ (np.asarray(T0.translation()) - p0_b)))
            x.update(bf.vel_key(s, k), D @ np.asarray(init.atVector(bf.vel_key(s, k)), float))
            if pb.bkey(s, k) != pb.bkey(s, b):
                x.update(pb.bkey(s, k), bias)
    for j, jt in enumerate(pb.joints):
        P = pb.names.index(jt.parent)
        key_l = bf.lever_key(lever_index[(jt.parent, j)])
        lev = np.asarray(x.atPoint3(key_l), float)
        for k in range(b + 1, k_end + 1):
            T = x.atPose3(bf.pose_key(P, k))
            x.update(bf.joint_key(j, k), np.asarray(T.translation(), float) + T.rotation().matrix() @ lev)


def chunk_bounds(kf_t: np.ndarray, chunk_s: float, overlap_s: float = OVERLAP_S) -> list[tuple[int, int]]:
    """(C1) keyframe ranges [a, b] of the chunks (the last one ends at the last keyframe)."""
    K = kf_t.size
    out, a = [], 0
    while True:
        b = int(np.searchsorted(kf_t, kf_t[a] + chunk_s, side="right")) - 1
        b = max(b, a + 2)
        if b >= K - 1 or kf_t[-1] - kf_t[b] < 0.5 * chunk_s:     # a short tail joins the last chunk
            out.append((a, K - 1))
            return out
        out.append((a, b))
        a_next = int(np.searchsorted(kf_t, kf_t[b] - overlap_s, side="left"))
        a = min(max(a_next, a + 1), b)


def chunked_start(pb, graph, chunk_s: float, optimize, overlap_s: float = OVERLAP_S):
    """(C1)–(C3): the stitched starting values for the full LM and the LM iterations per chunk."""
    bounds = chunk_bounds(pb.kf_t, float(chunk_s), overlap_s)
    x = gtsam.Values(pb.init)
    if len(bounds) == 1:
        return x, []
    spans = factor_spans(pb, graph)
    glob = np.flatnonzero(spans[:, 0] == -1)
    iters = []
    for c, (a, b) in enumerate(bounds):
        if c > 0:
            _propagate(pb, x, bounds[c - 1][1], b)
        sub = gtsam.NonlinearFactorGraph()
        for i in np.r_[glob, np.flatnonzero((spans[:, 0] >= a) & (spans[:, 1] <= b))].astype(int):
            sub.add(graph.at(int(i)))
        if c > 0:
            sub.push_back(_boundary_priors(pb, x, a))
        vals = gtsam.Values()
        for key in sub.keyVector():
            vals.insert(key, _get(x, key))
        sol, info = optimize(pb, sub, vals)
        iters.append(int(info["iterations"]))
        x.update(sol)                                 # x is a copy of pb.init: it holds every key
    return x, iters
