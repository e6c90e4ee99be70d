"""From a BVH joint hierarchy to an MVN-named `Skeleton` and its segment motion.

Mapping: each MVN segment is one BVH joint (its origin = the joint's position, its rotation = the
joint's world rotation times a constant fix, below). BVH joints that are not mapped are folded into
their nearest mapped ancestor: their offsets add up (at rest) and their own rotations are dropped, so
the MVN skeleton is rigid between mapped joints. Built-in mappings: `CMU` (the CMU Graphics Lab
skeleton of ``cmu_bvh/``) and `XSENS` (the Xsens MVN BVH export); the one whose joints all exist in
the file is used unless a mapping is given.

Segment frames. A BVH joint's world rotation nR_j (imugraph.io.bvh, eq. B3) is the identity in the
rest pose. The MVN segment frame must be the identity in the NEUTRAL pose (N-pose, arms down), so

    nR_seg(t) = nR_j(t) · R_fix,   R_fix = nR_j,restᵀ · nR_seg,rest = nR_seg,rest                    (M1)

where nR_seg,rest is the segment's orientation in the BVH rest pose: the identity for the trunk, head,
shoulder girdle and feet; for the long limb segments (upper arm, forearm, hand, upper leg, lower leg),
which hang straight down in the neutral pose, the smallest rotation taking −z to the segment's rest
direction (origin → distal end). This undoes a T-pose rest (Xsens export: arms along ±y) and CMU's
splayed rest legs (thighs ≈ 20° outwards), so that joint angles are zero in the neutral pose. Offsets and ends are the rest
vectors expressed in the rest segment frame, offset_i = nR_parent,restᵀ (p_i − p_parent)             (M2)
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import numpy as np

from imugraph.body.skeleton import FULL_BODY_SENSED, MVN_PARENT, MVN_SEGMENTS, Skeleton
from imugraph.errors import SessionError
from imugraph.geometry import expmap, quat_to_rotmat, rotmat_to_quat
from imugraph.io.bvh import Bvh, C_NF, read_bvh

CMU = {"Pelvis": "Hips", "L5": "lowerback", "T8": "Chest", "Neck": "lowerneck", "Head": "Head",
       "LeftShoulder": "LeftCollar", "LeftUpperArm": "LeftShoulder", "LeftForeArm": "LeftElbow",
       "LeftHand": "LeftWrist", "RightShoulder": "RightCollar", "RightUpperArm": "RightShoulder",
       "RightForeArm": "RightElbow", "RightHand": "RightWrist",
       "LeftUpperLeg": "LeftHip", "LeftLowerLeg": "LeftKnee", "LeftFoot": "LeftAnkle", "LeftToe": "LeftToe",
       "RightUpperLeg": "RightHip", "RightLowerLeg": "RightKnee", "RightFoot": "RightAnkle", "RightToe": "RightToe"}
XSENS = {"Pelvis": "Hips", "L5": "Chest", "L3": "Chest2", "T12": "Chest3", "T8": "Chest4", "Neck": "Neck",
         "Head": "Head", "RightShoulder": "RightCollar", "RightUpperArm": "RightShoulder",
         "RightForeArm": "RightElbow", "RightHand": "RightWrist", "LeftShoulder": "LeftCollar",
         "LeftUpperArm": "LeftShoulder", "LeftForeArm": "LeftElbow", "LeftHand": "LeftWrist",
         "RightUpperLeg": "RightHip", "RightLowerLeg": "RightKnee", "RightFoot": "RightAnkle",
         "RightToe": "RightToe", "LeftUpperLeg": "LeftHip", "LeftLowerLeg": "LeftKnee",
         "LeftFoot": "LeftAnkle", "LeftToe": "LeftToe"}
IDENTITY = {n: n for n in MVN_SEGMENTS}            # files written by imugraph.io.bvh.write_bvh
MAPPINGS = {"mvn": IDENTITY, "xsens": XSENS, "cmu": CMU}
_LIMBS = ("UpperArm", "ForeArm", "Hand", "UpperLeg", "LowerLeg")
_CHAIN = {p: c for c, p in MVN_PARENT.items() if not c.endswith(("Shoulder", "UpperLeg"))}  # distal neighbour


def choose_mapping(bvh: Bvh) -> dict:
    """The built-in mapping fully present in `bvh`, else the one matching most joints (restricted to them).

    Its Pelvis joint must be the file's root (SessionError otherwise): e.g. a lower-body file written
    by `write_bvh` maps by the identity onto its 7 segments.
    """
    best = max(MAPPINGS.values(), key=lambda m: (all(j in bvh.names for j in m.values()),
                                                 sum(j in bvh.names for j in m.values())))
    if best["Pelvis"] != bvh.names[0]:
        raise SessionError(bvh.source, "HIERARCHY", f"joints {list(bvh.names)[:8]}…",
                           "the joints of a CMU, Xsens MVN or imugraph BVH skeleton (or pass a mapping)")
    return {s: j for s, j in best.items() if j in bvh.names}


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation R with R·â = b̂ (3×3)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        return np.eye(3) if c > 0 else expmap(np.pi * np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0]))
    return expmap(axis / s * np.arctan2(s, c))


def _descendant_end(bvh: Bvh, j: int, mapped: set, rest: np.ndarray, ends: dict) -> Optional[np.ndarray]:
    """Distal point of joint j from its own End Site, else the farthest End Site reached through unmapped joints."""
    if j in ends:
        return ends[j]
    best, stack = None, [k for k, p in enumerate(bvh.parents) if p == j and k not in mapped]
    while stack:
        k = stack.pop()
        for cand in ([ends[k]] if k in ends else []) + [rest[k]]:
            if best is None or np.linalg.norm(cand - rest[j]) > np.linalg.norm(best - rest[j]):
                best = cand
        stack += [m for m, p in enumerate(bvh.parents) if p == k and m not in mapped]
    return best


def skeleton_from_bvh(bvh: Union[Bvh, str, Path], mapping: Optional[dict] = None,
                      units_m: Optional[float] = None) -> tuple[Skeleton, dict, np.ndarray]:
    """MVN-named skeleton of a BVH file.

    Args:
        bvh: a parsed Bvh or a path.
        mapping: MVN segment name → BVH joint name; None picks a built-in one (`choose_mapping`).
        units_m: metres per file unit; None detects it.
    Returns:
        (Skeleton, mapping used (present segments only), R_fix (S, 3, 3) of eq. (M1)).
    Raises:
        SessionError: unknown joints in the mapping, a root that is not mapped to Pelvis, a segment
        order incompatible with the BVH tree.
    """
    if not isinstance(bvh, Bvh):
        bvh = read_bvh(bvh)
    mapping = choose_mapping(bvh) if mapping is None else dict(mapping)
    for seg, joint in mapping.items():
        if joint not in bvh.names:
            raise SessionError(bvh.source, "mapping", f"{seg} → {joint!r}, not a joint of the file", "existing joints")
    order = [s for s in MVN_SEGMENTS if s in mapping] + sorted(s for s in mapping if s not in MVN_SEGMENTS)
    jidx = {s: bvh.index(mapping[s]) for s in order}
    if order[0] != "Pelvis" or jidx["Pelvis"] != 0:
        raise SessionError(bvh.source, "mapping", f"root {bvh.names[0]!r}, Pelvis → {mapping.get('Pelvis')!r}",
                           "Pelvis mapped to the BVH root joint")
    by_joint = {j: s for s, j in jidx.items()}
    scale = bvh.scale_to_m() if units_m is None else float(units_m)
    f_rest, f_ends = bvh.rest_positions()
    rest = scale * f_rest @ C_NF.T                                      # n frame, m
    ends = {j: scale * e @ C_NF.T for j, e in f_ends.items()}
    parents = []
    for s in order:
        a = bvh.parents[jidx[s]]
        while a >= 0 and a not in by_joint:
            a = bvh.parents[a]
        if s != "Pelvis" and (a < 0 or order.index(by_joint[a]) >= order.index(s)):
            raise SessionError(bvh.source, "mapping", f"{s} ({mapping[s]}) below {by_joint.get(a)}",
                               "a mapping whose segment order follows the BVH tree")
        parents.append(-1 if s == "Pelvis" else order.index(by_joint[a]))
    mapped = set(jidx.values())
    distal = {}
    for i, s in enumerate(order):
        j = jidx[s]
        nxt = _CHAIN.get(s)
        while nxt is not None and (nxt not in jidx or np.linalg.norm(rest[jidx[nxt]] - rest[j]) < 0.01):
            nxt = _CHAIN.get(nxt)                      # next segment along the limb/spine, ≥ 1 cm away
        cands = [rest[jidx[nxt]]] if nxt is not None else []
        if not cands:
            cands = [rest[jidx[c]] for c, p in zip(order, parents) if p == i]
            d = _descendant_end(bvh, j, mapped, rest, ends)
            cands += [] if d is None else [d]
        distal[s] = max(cands, key=lambda p: np.linalg.norm(p - rest[j])) if cands else rest[j]
    R_rest = np.tile(np.eye(3), (len(order), 1, 1))
    for i, s in enumerate(order):
        d = distal[s] - rest[jidx[s]]
        if s.endswith(_LIMBS) and np.linalg.norm(d) > 1e-6:
            R_rest[i] = _min_rotation(np.array([0.0, 0.0, -1.0]), d)                     # (M1), limbs down
    offsets = np.zeros((len(order), 3))
    for i, s in enumerate(order[1:], 1):
        p = parents[i]
        offsets[i] = R_rest[p].T @ (rest[jidx[s]] - rest[jidx[order[p]]])                 # (M2)
    seg_ends = np.array([R_rest[i].T @ (distal[s] - rest[jidx[s]]) for i, s in enumerate(order)])
    skel = Skeleton(names=tuple(order), parents=tuple(parents), offsets=offsets,
                    sensed=tuple(s for s in FULL_BODY_SENSED if s in order), ends=seg_ends)
    return skel, {s: mapping[s] for s in order}, R_rest


def segment_motion(bvh: Union[Bvh, str, Path], mapping: Optional[dict] = None, units_m: Optional[float] = None):
    """Segment orientations and origins of a BVH motion (M1), on its MVN skeleton.

    Returns:
        (skel, mapping, t (F,), n_quat (F, S, 4), n_pos (F, S, 3)); n_pos are the BVH joint positions
        (they differ from `skel.forward_kinematics` where folded joints rotate).
    """
    if not isinstance(bvh, Bvh):
        bvh = read_bvh(bvh)
    skel, mapping, R_fix = skeleton_from_bvh(bvh, mapping, units_m)
    t, q_j, p_j = bvh.world_poses(units_m)
    idx = [bvh.index(mapping[s]) for s in skel.names]
    nR = quat_to_rotmat(q_j[:, idx]) @ R_fix                                                # (M1)
    return skel, mapping, t, rotmat_to_quat(nR), p_j[:, idx]
