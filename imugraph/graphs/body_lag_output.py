"""The fixed lag's per-keyframe records and its causal per-sample output (split from body_incremental).

`_record` keeps what the filter knows right after keyframe k's update; `filtered_result` turns those records into
segment orientations and the root position per sample (gyro integrated forward from each keyframe's state).
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.factors import body as bf
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.graphs import body_lag_neck, body_neck
from imugraph.graphs.body import BodyProblem
from imugraph.graphs.body_init import rz
from imugraph.graphs.body_output import BodyResult, fill_segments, forward_kinematics


def _record(pb: BodyProblem, est: gtsam.Values, k: int, place_psi: tuple, bend: dict | None = None) -> dict:
    """What the filter knows right after keyframe k's update: keyframe k's sensor states, the biases and the
    sensor-to-segment rotations from the CURRENT estimate of the N-pose (heading becomes observable only
    once the subject moves, so these improve over time); `bend`: the neck's bend known then (body_lag_neck (L4))."""
    place, psi = place_psi
    S = len(pb.names)
    return {"nRs": np.stack([est.atPose3(bf.pose_key(s, k)).rotation().matrix() for s in range(S)]),
            "p": est.atPose3(bf.pose_key(0, k)).translation(), "v": est.atVector(bf.vel_key(0, k)),
            "b_gyr": np.stack([est.atConstantBias(pb.bkey(s, k)).gyroscope() for s in range(S)]),
            "place": place, "psi": psi, **({"bend": bend} if bend is not None else {})}


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
    per_kf = [r.get("bend") for r in records]
    if per_kf and all(b for b in per_kf):                            # lag_neck_stream: keyframe k's bend (L4)
        q_seg.update(body_lag_neck.apply_per_keyframe(per_kf, L, q_seg))
    else:
        q_seg.update(body_neck.apply_bend(bend or {}, q_seg))          # nR_u = nR_A · A_R_u (N5)
    n_quat = fill_segments(pb.skel, q_seg)
    n_pos = forward_kinematics(pb.skel, n_quat, root)
    return BodyResult(t, tuple(pb.skel.names), n_quat, n_pos,
                      {n: {"bRs": records[-1]["place"][n][0], "b_pos": records[-1]["place"][n][1]} for n in pb.names},
                      {"mode": "filtered", "npose_heading_deg": [float(np.rad2deg(r["psi"])) for r in records]})
