"""The unsensed neck in the fixed lag / iSAM2: the stream estimates the neck's constant bend itself (helper L22).

BodyOptions.lag_neck_stream (off by default). The batch reads the neck's bend (N5) of imugraph.graphs.body_neck from
the levers of its (N6) pass; helper L21's `lag_neck_from_bootstrap` read it once, from the bootstrap's (N6) pass, and
kept it for the whole stream — too few seconds of motion on CMU 131_02 (head 3.0–3.6 cm). Here the stream carries
the same model and keeps estimating those levers as the motion goes on:

(L1) bootstrap: the (N6) pass ((N8), (N9) as set) on the bootstrap's batch problem gives x_n; the stream starts from
     x_n (states, biases, levers, placements bRs from its N-pose), the neck's lumped-joint levers from (N9)'s
     magnetometer-free solution when that ran (the levers (N5) reads in the batch too).
(L2) the stream's anchor on those levers: σ = lag_neck_anchor_sigma_m (None: the 5 mm of every lever anchor), a
     diagonal stand-in for the bootstrap's marginal as in body_lag_boot.anchor.
(L3) the stream keeps the neck's lumped joint at lever_pass_bend_sigma_m (N8) in every keyframe's factors:

        J_k = nTs_A,k l_A,D + w,   J_k = nTs_D,k l_D,A + w',   w, w' ~ N(0, σ_N8² I)                    (B2), (N8)

(L4) each keyframe's output turns the neck with T8 by the bend (N5) of the CURRENT estimate of the levers, with the
     placements the output uses (the bootstrap's; with lag_bootstrap_marginal (L7) the current ones):  nR_u(t) = nR_A(t) · Rot(o_D → bR̂s_A (l̂_A,D − l̂_A,up) − o_u)                 (N5)
     The fixed lag's output of a keyframe uses the levers as they were when it left the window (smoothed at the
     lag), the filtered output those right after its own update: causal up to the lag. The levers are global
     keys (never marginalised), so all past keyframes' information on them stays in the window's prior.
(L8) lag_neck_mag_offset, with magnetometers and (N9): the stream cannot solve without its magnetometer factors, so
     (L4) reads its levers plus the offset the bootstrap measured between (N9)'s magnetometer-free levers and its own,
     l̂ + (l_N9 − l_x_n)_bootstrap (the levers themselves stay the magnetometer solution's, no (N9) substitution in (L1)).
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from imugraph.factors import body as bf
from imugraph.geometry import quat_mul, rotmat_to_quat
from imugraph.graphs import body_neck


def wanted(opts, bootstrap_s) -> bool:
    """Whether the stream runs (L1)–(L4): the option set, a bootstrap, a bend asked for, (N6) levers available."""
    return bool(opts.lag_neck_stream and bootstrap_s is not None and opts.unsensed_bend
                and opts.lever_prior_frame != "nominal")


def neck_lever_keys(pb, opts) -> list[int]:
    """Lever keys of the lumped joints of opts.unsensed_bend (both sides: A's and D's lever to that joint)."""
    joints = {j for j, *_ in body_neck.split_chains(pb, tuple(opts.unsensed_bend))}
    return [bf.lever_key(i) for i, (_, j, _) in enumerate(pb.levers) if j in joints]


def bootstrap_pass(pb_b, x_b: gtsam.Values, graph, opts) -> tuple[gtsam.Values, dict, dict | None]:
    """(L1): (x_n, bend (N5) of the bootstrap, the pass's info) — x_n the (N6) pass on the bootstrap problem pb_b from
    x_b, with the neck's lumped-joint levers taken from (N9)'s magnetometer-free values when that pass ran.
    (x_b, {}, None) when pb_b has no lumped joint. pb_b's options and levers are restored afterwards."""
    saved = pb_b.opts, list(pb_b.levers), pb_b.bend_values
    pb_b.opts = dataclasses.replace(opts, hinges=())
    try:
        x_n, info = body_neck.lever_pass(pb_b, x_b, graph)                                       # (N6), (N8), (N9)
        if info is None:
            return x_b, {}, None
        bend = body_neck.solved_bend(pb_b, x_n)                                                   # (N5)
        info = dict(info, levers=list(pb_b.levers))          # (N6)'s lever priors, for body_incremental (L7)
        x_out = gtsam.Values(x_n)
        if pb_b.bend_values is not None and opts.lag_neck_mag_offset:                            # (L8)
            info["lever_delta"] = {bf.lever_key(i): np.asarray(pb_b.bend_values.atPoint3(bf.lever_key(i)))
                                   - np.asarray(x_n.atPoint3(bf.lever_key(i))) for i in range(len(pb_b.levers))}
        elif pb_b.bend_values is not None:                                                        # (N9)'s levers
            for key in neck_lever_keys(pb_b, opts):
                x_out.update(key, pb_b.bend_values.atPoint3(key))
        return x_out, bend, info
    finally:
        pb_b.opts, pb_b.levers, pb_b.bend_values = saved


def stream_factors(pb, graph: gtsam.NonlinearFactorGraph, opts) -> None:
    """(L3): the neck's lumped joint factors in `graph` (one keyframe's, in place) at σ lever_pass_bend_sigma_m."""
    if opts.lever_pass_bend_sigma_m is not None:
        body_neck.bend_joint_sigma(pb, graph, tuple(opts.unsensed_bend), opts.lever_pass_bend_sigma_m)


def stream_bend(pb, est: gtsam.Values, place: dict, opts, lever_delta: dict | None = None) -> dict:
    """(L4): {link: (A, A_R_link)} the bend (N5) of the stream's current levers with the output's placements `place`;
    `lever_delta` (L8) {lever key: offset} added to the levers first."""
    if lever_delta:
        est = gtsam.Values(est)
        for key, d in lever_delta.items():
            if est.exists(key):
                est.update(key, np.asarray(est.atPoint3(key)) + d)
    return body_neck.graph_bend(pb, est, tuple(opts.unsensed_bend), place)


def apply_per_keyframe(bends: list, L: np.ndarray, q_seg: dict) -> dict:
    """{link: (N, 4) nR_link = nR_A · A_R_link,k} (N5) with keyframe k's bend for the L[k] samples it owns."""
    out = {}
    for link, (A, _) in bends[0].items():
        q_k = rotmat_to_quat(np.stack([b[link][1] for b in bends]))                               # (K, 4)
        out[link] = quat_mul(q_seg[A], np.repeat(q_k, L, axis=0))
    return out
