"""From a solved body graph to segment orientations and positions at every input sample.

1. N-pose heading ψ: the rotation about z between the skeleton's neutral joint centres and the estimated
   ones at the N-pose (`npose_heading`, O1; x forward, y left, z up); with < 2 joints, `npose_heading_deg`.
2. Sensor-to-segment rotation: in the N-pose nRb = Rz(ψ), so bRs = Rz(ψ)ᵀ nRs, averaged over the N-pose
   keyframes (chordal mean: SVD projection of the summed matrices). Sensor origin on its segment:
   b_pos = b_joint − bRs l, averaged over the sensor's joints.
3. Per sample between keyframes a and b: the gyro (minus the estimated bias) integrated forward from a and
   backward from b, blended by slerp with u = (i − a)/(b − a) (continuous at both keyframes).
4. Segments: nRb = nRs bRsᵀ; unsensed ones via imugraph.body.skeleton.fill_unsensed (non-strict: where no
   tie applies, the nearest sensed ancestor's orientation), or (BodyOptions.unsensed_bend) a single
   unsensed link turned with its upper neighbour by the bend the graph's levers imply (body_neck (N5));
   root origin = p_s + nRs (sRb (0 − b_pos)) with
   p_s Hermite-interpolated from keyframe positions and velocities; the other origins by forward kinematics
   with the skeleton's offsets.
5. Output frame: the graph's frame is fixed by the gauge (root sensor heading from its nominal placement),
   which is off by the unknown placement heading; the output is turned about z by Rz(ψ₀ − ψ) so that the body
   faces ψ₀ = `npose_heading_deg` in the N-pose (the MVN convention: facing +x), with or without magnetometers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from imugraph.factors import body as bf
from imugraph.geometry import quat_conj, quat_mul, quat_slerp, quat_to_rotmat, rotmat_to_quat, rotvec_to_quat
from imugraph.factors.body_axial import long_axis
from imugraph.graphs import body_chain, body_neck
from imugraph.graphs.body_axial import axial_angles
from imugraph.graphs.body_init import rz


@dataclass(frozen=True)
class BodyResult:
    """Estimated body motion.

    t (N,); names: all skeleton segments; n_quat (N, S, 4) segment → nav (w,x,y,z); n_pos (N, S, 3)
    segment origins, m; placements {sensed segment: {"bRs": (3,3), "b_pos": (3,)}}; info: solver details
    (timing, iterations, keyframe times, sensor biases, joint centres per keyframe, ...).
    """
    t: np.ndarray
    names: tuple
    n_quat: np.ndarray
    n_pos: np.ndarray
    placements: dict
    info: dict = field(default_factory=dict)


def project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _neutral_joint_centres(pb) -> np.ndarray:
    """(J, 3) joint centres (= child origins) in the neutral pose, root origin at 0 (offsets summed, K1)."""
    skel = pb.skel
    pos = np.zeros((len(skel.names), 3))
    for i, p in enumerate(skel.parents):
        if p >= 0:
            pos[i] = pos[p] + np.asarray(skel.offsets[i], float)
    return np.array([pos[skel.index(jt.child)] for jt in pb.joints]).reshape(-1, 3)


def npose_heading(pb, x: gtsam.Values, kfs: np.ndarray) -> float:
    """ψ of the N-pose (module docstring, step 1): the rotation about z that best maps the skeleton's neutral
    joint centres onto the estimated ones (horizontal parts, centroids removed),

        ψ = atan2(Σ_j (u_j × d_j)_z, Σ_j u_j · d_j),   u_j = P(c_j − c̄), d_j = P(J_j − J̄)          (O1)

    (2-D Procrustes; P drops z). With the hips only this is the heading of (J_LeftHip − J_RightHip) × z,
    the former rule; a ψ error δ conjugates every relative rotation (nRb_est = nRb Rz(δ)). Measured with
    benchmarks/body_sim_accuracy.py (17 IMUs, no magnetometers, seeds 0–2, geodesic joint RMSE): CMU 131_02
    worst joint hips-only 2.06/4.69/2.99° (elbows, neck) → all joints 1.11/3.15/0.83°; legs only or hips +
    shoulders no better overall; on the Xsens walk (seeds 0, 1) mean joint RMSE 0.40/0.34° → 0.50/0.47°
    (both far below target). Fewer than two joints: `npose_heading_deg`."""
    if len(pb.joints) < 2:
        return float(np.deg2rad(pb.opts.npose_heading_deg))
    c = _neutral_joint_centres(pb)
    J = np.mean([[x.atPoint3(bf.joint_key(j, k)) for j in range(len(pb.joints))] for k in kfs], axis=0)
    u, d = (c - c.mean(axis=0))[:, :2], (J - J.mean(axis=0))[:, :2]
    return float(np.arctan2(np.sum(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0]), np.sum(u * d)))          # (O1)


def estimate_placements(pb, x: gtsam.Values) -> tuple[dict, float]:
    """({segment: (bRs, b_pos)}, ψ) from the solution (module docstring, steps 1–2)."""
    kfs = np.array([k for k in np.flatnonzero(pb.kf <= pb.npose_idx[-1]) if x.exists(bf.pose_key(0, k))], int)
    kfs = kfs if kfs.size else np.array([0])            # (incremental: the N-pose keyframes seen so far)
    psi = npose_heading(pb, x, kfs)
    out = {}
    chained = body_chain.chain_joints(pb)                # their parent-side lever is unused (prior only)
    for s, name in enumerate(pb.names):
        M = sum(rz(psi).T @ x.atPose3(bf.pose_key(s, k)).rotation().matrix() for k in kfs)
        bRs = project_so3(M)
        b = [jt.b_parent if jt.parent == name else jt.b_child for j, jt in enumerate(pb.joints)
             if name in (jt.parent, jt.child) and not (jt.parent == name and j in chained)]
        ls = [x.atPoint3(bf.lever_key(i)) for i, (seg, j, _) in enumerate(pb.levers)
              if seg == name and not (pb.joints[j].parent == name and j in chained)]
        for bj, lj in body_chain.placement_levers(pb, x, name):
            b, ls = b + [bj], ls + [lj]
        b_pos = np.mean([bj - bRs @ l for bj, l in zip(b, ls)], axis=0) if ls else pb.setups[name].b_pos_nom
        out[name] = (bRs, b_pos)
    return out, psi


def sample_orientations(pb, x: gtsam.Values, s: int, name: str, bias_gyr: np.ndarray) -> np.ndarray:
    """(N, 4) nRs at every sample (bias_gyr (3,) or per sample (N, 3)): forward/backward gyro integration between keyframes, slerp-blended."""
    sess = pb.session.sensors[name]
    N = sess.t.size
    dq = rotvec_to_quat((sess.gyr - bias_gyr) * sess.dt[:, None])           # Exp((ω_i − b) dt_i)
    q_kf = rotmat_to_quat(np.stack([x.atPose3(bf.pose_key(s, k)).rotation().matrix() for k in range(pb.K)]))
    out = np.empty((N, 4))
    out[pb.kf] = q_kf
    a, b = pb.kf[:-1], pb.kf[1:]
    L = b - a
    for length in np.unique(L):                        # intervals of equal length, vectorised
        sel = np.flatnonzero(L == length)
        a_s = a[sel]
        fwd = [q_kf[sel]]                              # q_{a+m} = q_a ⊗ Π_{i<a+m} Exp((ω_i − b) dt_i)
        for m in range(1, length):
            fwd.append(quat_mul(fwd[-1], dq[a_s + m - 1]))
        bwd = [None] * (length + 1)
        bwd[length] = q_kf[sel + 1]                    # q_{a+m} = q_b ⊗ (Π_{a+m ≤ i < b} Exp(...))⁻¹
        for m in range(length - 1, 0, -1):
            bwd[m] = quat_mul(bwd[m + 1], quat_conj(dq[a_s + m]))
        for m in range(1, length):
            out[a_s + m] = quat_slerp(fwd[m], bwd[m], np.full(sel.size, m / length))
    return out


def _hermite(t: np.ndarray, kf_t: np.ndarray, p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cubic Hermite interpolation of keyframe positions p with velocities v at times t."""
    i = np.clip(np.searchsorted(kf_t, t, side="right") - 1, 0, kf_t.size - 2)
    h = kf_t[i + 1] - kf_t[i]
    u = ((t - kf_t[i]) / h)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    return h00 * p[i] + h10 * h[:, None] * v[i] + h01 * p[i + 1] + h11 * h[:, None] * v[i + 1]


def fill_segments(skel, n_quat_sensed: dict) -> np.ndarray:
    """(N, S, 4) for all segments: imugraph.body.skeleton.fill_unsensed (ties K2), non-strict: a segment with
    estimated segments on several branches below it turns with its nearest estimated ancestor (never raises
    for a skeleton whose root is sensed, e.g. BVH-derived ones with 21 segments)."""
    from imugraph.body.skeleton import fill_unsensed
    return fill_unsensed(skel, n_quat_sensed, strict=False)


def forward_kinematics(skel, n_quat: np.ndarray, n_root: np.ndarray) -> np.ndarray:
    """(N, S, 3) segment origins: p_i = p_parent + nRb_parent · offset_i."""
    R = quat_to_rotmat(n_quat)
    p = np.empty(n_quat.shape[:2] + (3,))
    for i, par in enumerate(skel.parents):
        p[:, i] = n_root if par < 0 else p[:, par] + R[:, par] @ np.asarray(skel.offsets[i], float)
    return p


def make_result(pb, x: gtsam.Values, info: dict) -> BodyResult:
    """BodyResult at every input sample (module docstring, steps 1–4)."""
    place, psi = estimate_placements(pb, x)
    t = np.asarray(pb.session.t, float)
    q_seg, biases, axial = {}, {}, {}
    owner = np.clip(np.searchsorted(pb.kf, np.arange(t.size), side="right") - 1, 0, pb.K - 1)   # sample → keyframe
    for s, name in enumerate(pb.names):
        b_kf = [x.atConstantBias(pb.bkey(s, k)) for k in range(pb.K)]
        acc_kf = np.stack([np.asarray(b.accelerometer()) for b in b_kf])
        gyr_kf = np.stack([np.asarray(b.gyroscope()) for b in b_kf])
        biases[name] = {"acc": acc_kf.mean(axis=0), "gyr": gyr_kf.mean(axis=0), "acc_kf": acc_kf, "gyr_kf": gyr_kf}
        q_s = sample_orientations(pb, x, s, name, gyr_kf[owner])        # (N, 3): each sample its segment's bias
        q_seg[name] = quat_mul(q_s, quat_conj(rotmat_to_quat(place[name][0])))     # nRb = nRs bRsᵀ
        theta = axial_angles(pb, x, name)                   # soft axial rotation: nRb = nRs bRsᵀ Exp(−θ â) (S1)
        if theta is not None:
            q_seg[name] = quat_mul(q_seg[name], rotvec_to_quat(-theta[:, None] * long_axis(pb.skel, name)))
            axial[name] = theta
        if s == 0:
            root_q = q_s
    q_seg.update(body_chain.link_orientations(pb, x, q_seg))           # estimated unsensed links (C1)–(C4)
    if not body_chain.active(pb):
        q_seg.update(body_neck.link_orientations(pb, x, q_seg))        # the graph's constant bend (N5), opt-in
    n_quat = fill_segments(pb.skel, q_seg)
    nRg = rz(np.deg2rad(pb.opts.npose_heading_deg) - psi)                    # graph frame → output frame (step 5)
    q_out = rotmat_to_quat(nRg)
    n_quat = quat_mul(np.broadcast_to(q_out, n_quat.shape), n_quat)
    kf_t = t[pb.kf]
    p_kf = np.stack([x.atPose3(bf.pose_key(0, k)).translation() for k in range(pb.K)])
    v_kf = np.stack([x.atVector(bf.vel_key(0, k)) for k in range(pb.K)])
    p_s = _hermite(t, kf_t, p_kf, v_kf)
    bRs, b_pos = place[pb.names[0]]
    n_root = (p_s + quat_to_rotmat(root_q) @ (bRs.T @ (-b_pos))) @ nRg.T
    n_pos = forward_kinematics(pb.skel, n_quat, n_root)
    J = np.stack([[x.atPoint3(bf.joint_key(j, k)) for j in range(len(pb.joints))] for k in range(pb.K)]) \
        if pb.joints else np.zeros((pb.K, 0, 3))
    J = J @ nRg.T
    info = dict(info, graph_npose_heading_deg=float(np.rad2deg(psi)), graph_to_output=nRg, kf_t=kf_t, biases=biases,
                joint_names=[jt.name for jt in pb.joints], joint_centres=J, axial_theta=axial,
                levers={f"{seg}@{pb.joints[j].name}": x.atPoint3(bf.lever_key(i))
                        for i, (seg, j, _) in enumerate(pb.levers)})
    placements = {n: {"bRs": place[n][0], "b_pos": place[n][1]} for n in pb.names}
    return BodyResult(t, tuple(pb.skel.names), n_quat, n_pos, placements, info)
