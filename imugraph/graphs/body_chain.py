"""Unsensed links between two sensed segments as estimated segments (option `BodyOptions.unsensed_sigma_rad`).

Without the option a chain of unsensed segments between a sensed segment A and the single sensed segment D
below it (the neck between T8 and Head; L5, L3, T12 between Pelvis and T8) is lumped into one soft joint
whose parent side is fixed in A's frame (imugraph.graphs.body_model.body_joints: the chain rigid with A), and
the output turns the links by the ties (K2) of imugraph.body.skeleton. With the option, every link u_1 … u_m
of such a chain gets a segment pose U(u,k) = nTb_u per keyframe (origin at its proximal joint, frame = segment
frame), held by C++ factors only (the fast C++ LM stays usable):

    q_1 = nTs_A · l_A        = U_1 · z_1          (C1)  first link's proximal joint, l_A ~ N(l_A,nom, σ_l²)
    q_i = U_{i−1} · o_i      = U_i · z_i          (C2)  joints along the chain, o_i ~ N(offset_i, σ_o²)
    J_D = U_m · o_D          = nTs_D · l_D        (C3)  the lumped joint's centre (D's origin), its child side
    Log(bR_A·nRs_Aᵀ nR_1), Log(nR_iᵀ nR_{i+1}), Log(nR_mᵀ nRs_D bR_Dᵀ) ~ N(0, σ² I)                  (C4)

    Log(nR̂_uᵀ nR_u) ~ N(0, σ² I),  nR̂_u = slerp(nR_A, nR_D, i/(m+1)) of the FIRST pass (fixed)   (C4')
    (C4') at the N-pose keyframes with σ_N = unsensed_npose_sigma_rad (every segment aligned there)  (C5)
    (C4') with σ_k = σ + g·θ_k, θ_k = |Log(nR_Aᵀ nR_D)| (first pass), g = unsensed_sigma_gain       (C6)

(z_i ~ N(0, (0.1 mm)²): the link's origin; all joints σ = joint_sigma_m.) (C4) is the relative rotation shared
evenly among the m+1 joints of the chain: without other evidence its minimum puts every link on the geodesic
between A and D at the fraction of the joints passed — exactly the ties (K2) — while the positions (C1)–(C3),
with D's sensor position integrated from its accelerometer, let the chain bend the way the motion says (a neck
that stays with T8 while the head nods). (C4) is a BetweenFactorPose3 with σ on the rotation and 1 km on the
translation (a rotation-only prior). It needs the sensor-to-segment rotations bRs, so like the hinges it is
emitted in a second pass (from the first pass's N-pose estimate `estimate_placements`), batch only; the
output's link orientations come from U: Δ_k = nR_Aᵀ nR_u at keyframes, slerp-interpolated between them,
nR_u(t) = nR_A(t) Δ(t) (`link_orientations`). Chains with no sensed segment below (toes) keep their tie.

Why (C4') and (C5) (`unsensed_prior="fixed"`); numbers from benchmarks/body_sim_accuracy.py, docs/results_issue4.md
session 16: (C4) also pulls the two SENSED neighbours towards each other — the head is a leaf whose heading the
joints see weakly: CMU 131_02 seed 0, σ 20°, the T8→Head joint RMSE went 0.22° → 4.98° and the head stayed 8.2 cm
off; (C4') leaves them alone. The positions carry little information on how a bend is shared along the chain: to
first order a link turned by u·θ with the distal lever l_D is the same motion as one turned by u'·θ with
l_D + (u' − u)·o_D, so only the lever priors tell them apart, and σ must be wide (hundreds of degrees: a
regulariser, not a belief) for the data to move the neck off the tie; where A and D do not turn relative to
each other (the MVN walk's T8 and Head) a constant link rotation is invisible and a wide σ lets it wander (worst
head over 5 seeds 1.88 → 3.33 cm at σ 1000°), which the N-pose anchor (C5) only partly stops (3.06 cm).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph.factors import body as bf
from imugraph.geometry import quat_conj, quat_mul, quat_slerp, quat_to_rotmat, rotmat_to_quat

_STRIDE = 10_000_000
ORIGIN_SIGMA_M = 1e-4          # z_i: the link's own origin (a definition, not a measurement)
FREE_TRANSLATION_SIGMA_M = 1e3  # (C4) translation part: no information


def link_pose_key(u: int, k: int) -> int:
    """U(u,k): Pose3 nTb of unsensed link u (index over all chains' links) at keyframe k."""
    return gtsam.symbol("u", u * _STRIDE + k)


def link_joint_key(u: int, k: int) -> int:
    """Q(u,k): Point3 proximal joint of link u at keyframe k, n, m."""
    return gtsam.symbol("q", u * _STRIDE + k)


def chain_lever_key(i: int) -> int:
    """N(i): Point3 constant of the chains (l_A, o_i, o_D or z_i), m."""
    return gtsam.symbol("n", i)


@dataclass(frozen=True)
class Chain:
    """Unsensed links between sensed A (parent) and D (child) of the lumped joint `joint` (index in pb.joints).

    links: unsensed segment names, proximal first; first: global link index of links[0]; levers: chain lever
    indices (l_A, z_1, o_2, z_2, …, o_D) and their prior means `lever_nom` and σ `lever_sigma`."""
    joint: int
    parent: str
    child: str
    links: tuple
    first: int
    levers: tuple
    lever_nom: tuple
    lever_sigma: tuple


def active(pb) -> bool:
    return getattr(pb, "chains", None) is not None


def make_chains(pb, place: dict) -> list[Chain]:
    """The chains of pb's lumped joints, with prior means from the first pass's placements {seg: (bRs, b_pos)}."""
    skel, o = pb.skel, pb.opts
    lever_sigma = o.lever_sigma_m if o.lever_sigma_m is not None else 0.07
    out, n_link, n_lever = [], 0, 0
    for j, jt in enumerate(pb.joints):
        if not jt.lumped or (o.unsensed_chains and jt.child not in o.unsensed_chains):
            continue
        links, i = [], skel.parents[skel.index(jt.child)]
        while skel.names[i] != jt.parent:
            links.insert(0, skel.names[i])
            i = skel.parents[i]
        bRs_A, b_pos_A = place[jt.parent]
        nom = [bRs_A.T @ (np.asarray(skel.offsets[skel.index(links[0])], float) - b_pos_A)]   # l_A (C1)
        sig = [lever_sigma]
        for m, u in enumerate(links):
            if m > 0:
                nom.append(np.asarray(skel.offsets[skel.index(u)], float))                 # o_i (C2)
                sig.append(o.chain_offset_sigma_m)
            nom.append(np.zeros(3))                                                         # z_i
            sig.append(ORIGIN_SIGMA_M)
        nom.append(np.asarray(skel.offsets[skel.index(jt.child)], float))                  # o_D (C3)
        sig.append(o.chain_offset_sigma_m)
        out.append(Chain(j, jt.parent, jt.child, tuple(links), n_link, tuple(range(n_lever, n_lever + len(nom))),
                         tuple(nom), tuple(sig)))
        n_link += len(links)
        n_lever += len(nom)
    return out


def chain_joints(pb) -> set:
    """Indices of pb.joints whose parent side (C1)–(C3) replace (only the child side (B2) is kept)."""
    return {c.joint for c in pb.chains} if active(pb) else set()


def _rot_prior(key_a: int, key_b: int, aRb: np.ndarray, sigma: float) -> gtsam.BetweenFactorPose3:
    """(C4): Log(aRb_measured⁻¹ nR_aᵀ nR_b) ~ N(0, σ² I), translation free."""
    model = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma), np.full(3, FREE_TRANSLATION_SIGMA_M)])
    return gtsam.BetweenFactorPose3(key_a, key_b, gtsam.Pose3(gtsam.Rot3(aRb), np.zeros(3)), model)


def _end_rotations(pb, x: gtsam.Values, place: dict, c: Chain) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3, 3) segment orientations nRb = nRs bRsᵀ of the chain's sensed ends A, D in the solution `x`."""
    sA, sD = pb.names.index(c.parent), pb.names.index(c.child)
    RA = np.stack([x.atPose3(bf.pose_key(sA, k)).rotation().matrix() for k in range(pb.K)]) @ place[c.parent][0].T
    RD = np.stack([x.atPose3(bf.pose_key(sD, k)).rotation().matrix() for k in range(pb.K)]) @ place[c.child][0].T
    return RA, RD


def tie_targets(pb, x: gtsam.Values, place: dict) -> dict:
    """{global link index: (K, 3, 3)} the ties (K2) of the first pass's solution `x`: nR_u = slerp(nR_A, nR_D,
    m/(n+1)) for link m = 1…n (the fixed target of (C4'))."""
    out = {}
    for c in pb.chains:
        RA, RD = _end_rotations(pb, x, place, c)
        qA, qD = rotmat_to_quat(RA), rotmat_to_quat(RD)
        n = len(c.links)
        for m in range(n):
            out[c.first + m] = quat_to_rotmat(quat_slerp(qA, qD, np.full(pb.K, (m + 1) / (n + 1))))
    return out


def tie_angles(pb, x: gtsam.Values, place: dict) -> dict:
    """{global link index: (K,)} θ_k = |Log(nR_Aᵀ nR_D)| of the first pass, rad (the chain's total bend, C6)."""
    out = {}
    for c in pb.chains:
        RA, RD = _end_rotations(pb, x, place, c)
        th = [np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(RA[k].T @ RD[k]))) for k in range(pb.K)]
        for m in range(len(c.links)):
            out[c.first + m] = np.asarray(th)
    return out


def chain_factors_at(pb, k: int, place: dict) -> gtsam.NonlinearFactorGraph:
    """(C1)–(C4) of keyframe k (k = 0 also the lever priors); `place` = pb.chain_place {seg: (bRs, b_pos)}."""
    g = gtsam.NonlinearFactorGraph()
    if not active(pb):
        return g
    o = pb.opts
    jm = gtsam.noiseModel.Isotropic.Sigma(3, o.joint_sigma_m if o.joint_sigma_m is not None else 0.003)
    for c in pb.chains:
        if k == 0:
            for i, l_nom, sig in zip(c.levers, c.lever_nom, c.lever_sigma):
                g.add(gtsam.PriorFactorPoint3(chain_lever_key(i), l_nom, gtsam.noiseModel.Isotropic.Sigma(3, sig)))
        A, D = bf.pose_key(pb.names.index(c.parent), k), bf.pose_key(pb.names.index(c.child), k)
        lv = iter(c.levers)
        prev = A
        for m in range(len(c.links)):
            U, q = link_pose_key(c.first + m, k), link_joint_key(c.first + m, k)
            g.add(gtsam.ReferenceFrameFactorPoint3Pose3(chain_lever_key(next(lv)), prev, q, jm))   # (C1), (C2)
            g.add(gtsam.ReferenceFrameFactorPoint3Pose3(chain_lever_key(next(lv)), U, q, jm))      # z_i
            if o.unsensed_prior == "shared":
                g.add(_rot_prior(prev, U, place[c.parent][0].T if m == 0 else np.eye(3), o.unsensed_sigma_rad))  # (C4)
            else:                                                                                           # (C4')
                sig = o.unsensed_sigma_rad
                if o.unsensed_sigma_gain is not None:                 # (C6) σ_k = σ + gain·θ_k
                    sig = sig + o.unsensed_sigma_gain * pb.chain_angles[c.first + m][k]
                if o.unsensed_npose_sigma_rad is not None and pb.kf[k] <= pb.npose_idx[-1]:
                    sig = o.unsensed_npose_sigma_rad                  # N-pose: every segment aligned (C5)
                target = gtsam.Pose3(gtsam.Rot3(pb.chain_targets[c.first + m][k]), np.zeros(3))
                model = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sig), np.full(3, FREE_TRANSLATION_SIGMA_M)])
                g.add(gtsam.PriorFactorPose3(U, target, model))
            prev = U
        J = bf.joint_key(c.joint, k)
        g.add(gtsam.ReferenceFrameFactorPoint3Pose3(chain_lever_key(next(lv)), prev, J, jm))          # (C3)
        if o.unsensed_prior == "shared":
            g.add(_rot_prior(prev, D, place[c.child][0], o.unsensed_sigma_rad))                               # (C4)
    return g


def insert_initial(pb, x: gtsam.Values, place: dict) -> gtsam.Values:
    """A copy of the first pass's `x` with the chain variables: links on the ties' geodesic (K2), positions by
    forward kinematics from A's sensor with the prior levers."""
    out = gtsam.Values(x)
    if not active(pb):
        return out
    for c in pb.chains:
        for i, l in zip(c.levers, c.lever_nom):
            out.insert(chain_lever_key(i), np.asarray(l, float))
        sA, n = pb.names.index(c.parent), len(c.links)
        RA, RD = _end_rotations(pb, x, place, c)
        for k in range(pb.K):
            qA, qD = rotmat_to_quat(RA[k]), rotmat_to_quat(RD[k])
            p = x.atPose3(bf.pose_key(sA, k)).transformFrom(np.asarray(c.lever_nom[0], float))
            for m in range(n):
                R = gtsam.Rot3.Quaternion(*quat_slerp(qA, qD, np.array((m + 1) / (n + 1))))
                out.insert(link_pose_key(c.first + m, k), gtsam.Pose3(R, p))
                out.insert(link_joint_key(c.first + m, k), np.asarray(p, float))
                off = c.lever_nom[2 * m + 2] if m + 1 < n else c.lever_nom[-1]
                p = p + R.matrix() @ np.asarray(off, float)
    return out


def link_orientations(pb, x: gtsam.Values, q_seg: dict) -> dict:
    """{link name: (N, 4) nRb in the graph frame} from the solution (module docstring), given the sensed
    segments' per-sample orientations q_seg (graph frame)."""
    if not active(pb) or not x.exists(link_pose_key(0, 0)):
        return {}
    N = np.asarray(pb.session.t).size
    a = np.clip(np.searchsorted(pb.kf, np.arange(N), side="right") - 1, 0, pb.K - 2)
    frac = np.clip((np.arange(N) - pb.kf[a]) / np.maximum(pb.kf[a + 1] - pb.kf[a], 1), 0.0, 1.0)
    out = {}
    for c in pb.chains:
        qA_kf = q_seg[c.parent][pb.kf]
        for m, name in enumerate(c.links):
            qU = rotmat_to_quat(np.stack([x.atPose3(link_pose_key(c.first + m, k)).rotation().matrix()
                                          for k in range(pb.K)]))
            delta = quat_mul(quat_conj(qA_kf), qU)                                # Δ_k = nR_Aᵀ nR_u
            d = quat_slerp(delta[a], delta[a + 1], frac) if pb.K > 1 else np.broadcast_to(delta[0], (N, 4))
            out[name] = quat_mul(q_seg[c.parent], d)
    return out


def placement_levers(pb, x: gtsam.Values, name: str) -> list:
    """[(b_joint, s_l)] of the chains' first levers l_A on sensor `name` (for its b_pos, body_output)."""
    if not active(pb):
        return []
    return [(np.asarray(pb.skel.offsets[pb.skel.index(c.links[0])], float), x.atPoint3(chain_lever_key(c.levers[0])))
            for c in pb.chains if c.parent == name and x.exists(chain_lever_key(c.levers[0]))]
