"""Kinematic body models: a tree of rigid segments with Xsens MVN names (DESIGN.md, `mocap.npz`).

Conventions (docs: body_api): navigation frame n is z up, x forward, y left, metres. Each segment
frame b has its origin at the segment's PROXIMAL joint and, in the neutral pose (standing N-pose, arms
down, facing +x), is aligned with n. A pose is therefore the rotation nRb of every segment plus the
root (Pelvis) origin, and the joint positions follow by forward kinematics

    n_p_i = n_p_parent(i) + nR_parent(i) · offset_i                                          (K1)

with offset_i the (constant) origin of segment i in its parent's frame.

Unsensed segments are tied to their neighbours (`fill_unsensed`, rules from the tree by `tie_rules`): an
unsensed segment u between its nearest given ancestor A and the single given segment D below it (reached
through unsensed segments only) turns by the fraction of the joints passed,

    nR_u = slerp(nR_A, nR_D, (depth u − depth A)/(depth D − depth A)),                        (K2)

and one with nothing given below it turns with A. On the MVN body this gives
nR_L5 = slerp(nR_Pelvis, nR_T8, 1/4), nR_L3 = … 1/2, nR_T12 = … 3/4, nR_Neck = slerp(nR_T8, nR_Head, 1/2),
nR_Toe = nR_Foot (`TIES`); on the CMU skeleton (no L3, T12) nR_L5 = slerp(nR_Pelvis, nR_T8, 1/2). An
unsensed segment with several given branches below it (e.g. T8 missing: Head and both shoulders) has no
rule: SessionError naming it (or, strict=False, it turns with A).

Anthropometry of `full_body`: segment lengths as fractions of body height H from Winter,
"Biomechanics and Motor Control of Human Movement" (4th ed., 2009, Fig. 4.1): hip-joint height
0.530 H, knee 0.285 H, ankle 0.039 H, shoulder 0.818 H, chin 0.870 H; hip width 0.191 H, shoulder
width 0.259 H, upper arm 0.186 H, forearm 0.146 H, hand 0.108 H, foot length 0.152 H. The trunk
between the hip-joint level and the shoulder level is split evenly into L5, L3, T12 (0.057 H each,
an assumption; L5's origin sits 0.03 H above and 0.02 H behind the hip centres) and T8 up to the neck
base at 0.83 H.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import quat_normalize, quat_slerp, quat_to_rotmat

MVN_SEGMENTS = ("Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head",
                "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
                "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand",
                "RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToe",
                "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe")
MVN_PARENT = {"L5": "Pelvis", "L3": "L5", "T12": "L3", "T8": "T12", "Neck": "T8", "Head": "Neck",
              "RightShoulder": "T8", "RightUpperArm": "RightShoulder", "RightForeArm": "RightUpperArm",
              "RightHand": "RightForeArm", "LeftShoulder": "T8", "LeftUpperArm": "LeftShoulder",
              "LeftForeArm": "LeftUpperArm", "LeftHand": "LeftForeArm", "RightUpperLeg": "Pelvis",
              "RightLowerLeg": "RightUpperLeg", "RightFoot": "RightLowerLeg", "RightToe": "RightFoot",
              "LeftUpperLeg": "Pelvis", "LeftLowerLeg": "LeftUpperLeg", "LeftFoot": "LeftLowerLeg",
              "LeftToe": "LeftFoot"}
FULL_BODY_SENSED = ("Pelvis", "T8", "Head", "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
                    "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand", "RightUpperLeg",
                    "RightLowerLeg", "RightFoot", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot")
LOWER_BODY = ("Pelvis", "RightUpperLeg", "RightLowerLeg", "RightFoot", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot")
# (K2) on the MVN body with the 17 sensors (what `tie_rules` derives): segment -> (a, b, u), nR = slerp(nR_a, nR_b, u)
TIES = {"L5": ("Pelvis", "T8", 0.25), "L3": ("Pelvis", "T8", 0.5), "T12": ("Pelvis", "T8", 0.75),
        "Neck": ("T8", "Head", 0.5), "RightToe": ("RightFoot", "RightFoot", 0.0),
        "LeftToe": ("LeftFoot", "LeftFoot", 0.0)}
_SRC = "<imugraph.body.skeleton>"


@dataclass(frozen=True)
class Skeleton:
    """A tree of rigid segments (see the module docstring for frames).

    Attributes:
        names: (S,) segment names, parents before children; names[0] is the root.
        parents: (S,) parent index per segment, -1 for the root.
        offsets: (S, 3) origin of each segment in its parent's frame, m (root: zeros).
        sensed: names of the segments carrying an IMU.
        ends: (S, 3) distal end point of each segment in its own frame, m.
    """

    names: tuple
    parents: tuple
    offsets: np.ndarray
    sensed: tuple
    ends: np.ndarray

    def __post_init__(self) -> None:
        S = len(self.names)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "parents", tuple(int(p) for p in self.parents))
        object.__setattr__(self, "sensed", tuple(self.sensed))
        off, ends = np.asarray(self.offsets, float), np.asarray(self.ends, float)
        object.__setattr__(self, "offsets", off)
        object.__setattr__(self, "ends", ends)
        if len(self.parents) != S or off.shape != (S, 3) or ends.shape != (S, 3) or S == 0:
            raise SessionError(_SRC, "shapes", f"{S} names, {len(self.parents)} parents, offsets {off.shape}, "
                               f"ends {ends.shape}", "one parent, offset and end per segment")
        if self.parents[0] != -1 or any(not (0 <= p < i) for i, p in enumerate(self.parents) if i > 0):
            raise SessionError(_SRC, "parents", str(self.parents), "-1 for names[0], earlier indices after")
        missing = [s for s in self.sensed if s not in self.names]
        if missing or len(set(self.names)) != S:
            raise SessionError(_SRC, "names", f"duplicates or unknown sensed {missing}", "unique segment names")

    def index(self, name: str) -> int:
        """Index of segment `name` (SessionError when absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise SessionError(_SRC, "segment", repr(name), f"one of {list(self.names)}") from None

    def children(self, name: str) -> list[str]:
        """Names of the direct children of `name`."""
        i = self.index(name)
        return [n for n, p in zip(self.names, self.parents) if p == i]

    @property
    def sensed_index(self) -> np.ndarray:
        """(len(sensed),) indices of the sensed segments."""
        return np.array([self.index(s) for s in self.sensed], int)

    def forward_kinematics(self, n_quat: np.ndarray, n_root: np.ndarray) -> np.ndarray:
        """Segment origins in n, eq. (K1).

        Args:
            n_quat: (T, S, 4) segment → n rotations w,x,y,z.
            n_root: (T, 3) root origin in n, m.
        Returns:
            (T, S, 3) segment origins in n, m.
        """
        n_quat, n_root = np.asarray(n_quat, float), np.asarray(n_root, float)
        S = len(self.names)
        if n_quat.ndim != 3 or n_quat.shape[1:] != (S, 4) or n_root.shape != (n_quat.shape[0], 3):
            raise SessionError(_SRC, "n_quat/n_root", f"{n_quat.shape}, {n_root.shape}", f"(T, {S}, 4) and (T, 3)")
        nR = quat_to_rotmat(n_quat)
        pos = np.empty(n_quat.shape[:2] + (3,))
        pos[:, 0] = n_root
        for i in range(1, S):
            p = self.parents[i]
            pos[:, i] = pos[:, p] + nR[:, p] @ self.offsets[i]                          # (K1)
        return pos

    def neutral_positions(self) -> np.ndarray:
        """(S, 3) segment origins in the neutral pose with the root at the origin (offsets summed)."""
        pos = np.zeros((len(self.names), 3))
        for i in range(1, len(self.names)):
            pos[i] = pos[self.parents[i]] + self.offsets[i]
        return pos

    def subset(self, names: Iterable[str]) -> "Skeleton":
        """The skeleton restricted to `names` (kept in this skeleton's order).

        A kept segment's parent is its nearest kept ancestor; its offset is the sum of the offsets of the
        removed segments in between (valid because all frames coincide in the neutral pose). The first
        kept segment must be an ancestor of all others.
        """
        keep = [n for n in self.names if n in set(names)]
        unknown = sorted(set(names) - set(self.names))
        if unknown or not keep:
            raise SessionError(_SRC, "subset", f"unknown or no segments {unknown}", f"names from {list(self.names)}")
        neutral = self.neutral_positions()
        kidx = [self.index(n) for n in keep]
        parents, offsets = [-1], [np.zeros(3)]
        for i in kidx[1:]:
            a = self.parents[i]
            while a >= 0 and a not in kidx:
                a = self.parents[a]
            if a < 0:
                raise SessionError(_SRC, "subset", f"{self.names[i]} has no kept ancestor", f"{keep[0]} above all")
            parents.append(kidx.index(a))
            offsets.append(neutral[i] - neutral[a])
        return Skeleton(names=tuple(keep), parents=tuple(parents), offsets=np.array(offsets),
                        sensed=tuple(s for s in self.sensed if s in keep), ends=self.ends[kidx].copy())


def _full_body_geometry(H: float) -> tuple[dict, dict]:
    """Offsets (in the parent frame) and distal ends (own frame) of the 23 MVN segments for height H."""
    hip_w, sh_w = 0.191 * H, 0.259 * H
    trunk = 0.057 * H                          # L5, L3, T12 lengths
    t8_z = (0.03 + 3 * 0.057) * H              # T8 origin above the pelvis origin (0.731 H from the floor)
    t8_len = 0.83 * H - 0.530 * H - t8_z      # T8 origin → neck base (C7) at 0.83 H
    foot = 0.152 * H
    off = {"Pelvis": (0, 0, 0), "L5": (-0.02 * H, 0, 0.03 * H), "L3": (0, 0, trunk), "T12": (0, 0, trunk),
           "T8": (0, 0, trunk), "Neck": (0, 0, t8_len), "Head": (0, 0, 0.04 * H)}
    ends = {"Pelvis": off["L5"], "L5": off["L3"], "L3": off["T12"], "T12": off["T8"], "T8": off["Neck"],
            "Neck": off["Head"], "Head": (0.01 * H, 0, 0.13 * H)}
    sh_z = (0.818 - 0.530) * H - t8_z - 0.005 * H      # shoulder-girdle origin in T8 (joints at 0.818 H)
    for side, s in (("Right", -1.0), ("Left", 1.0)):
        off[f"{side}Shoulder"] = (0, s * 0.015 * H, sh_z)
        off[f"{side}UpperArm"] = (0, s * (sh_w / 2 - 0.015 * H), 0.005 * H)
        off[f"{side}ForeArm"] = (0, 0, -0.186 * H)
        off[f"{side}Hand"] = (0, 0, -0.146 * H)
        off[f"{side}UpperLeg"] = (0, s * hip_w / 2, 0)
        off[f"{side}LowerLeg"] = (0, 0, -(0.530 - 0.285) * H)
        off[f"{side}Foot"] = (0, 0, -(0.285 - 0.039) * H)
        off[f"{side}Toe"] = (0.5 * foot, 0, -0.029 * H)           # ankle → ball of the foot
        ends.update({f"{side}Shoulder": off[f"{side}UpperArm"], f"{side}UpperArm": off[f"{side}ForeArm"],
                     f"{side}ForeArm": off[f"{side}Hand"], f"{side}Hand": (0, 0, -0.108 * H),
                     f"{side}UpperLeg": off[f"{side}LowerLeg"], f"{side}LowerLeg": off[f"{side}Foot"],
                     f"{side}Foot": off[f"{side}Toe"], f"{side}Toe": (0.25 * foot, 0, -0.01 * H)})
    return off, ends


def full_body(height_m: float = 1.75) -> Skeleton:
    """The 23-segment MVN body with 17 sensed segments, Winter's proportions (module docstring).

    Args:
        height_m: body height H, m (0.5–2.5).
    Raises:
        SessionError: implausible height.
    """
    if not (np.isfinite(height_m) and 0.5 <= height_m <= 2.5):
        raise SessionError(_SRC, "height_m", str(height_m), "a body height between 0.5 and 2.5 m")
    off, ends = _full_body_geometry(float(height_m))
    parents = tuple(-1 if n == "Pelvis" else MVN_SEGMENTS.index(MVN_PARENT[n]) for n in MVN_SEGMENTS)
    return Skeleton(names=MVN_SEGMENTS, parents=parents, offsets=np.array([off[n] for n in MVN_SEGMENTS], float),
                    sensed=FULL_BODY_SENSED, ends=np.array([ends[n] for n in MVN_SEGMENTS], float))


def lower_body(height_m: float = 1.75) -> Skeleton:
    """Pelvis and both legs down to the feet: 7 segments, all sensed (a subset of `full_body`)."""
    return full_body(height_m).subset(LOWER_BODY)


def _depths(skel) -> list[int]:
    d = []
    for p in skel.parents:
        d.append(0 if p < 0 else d[p] + 1)
    return d


def tie_rules(skel, given) -> dict:
    """{unsensed segment: (segment a, segment b, fraction u)} of eq. (K2) for the segments not in `given`.

    Raises:
        SessionError: the root not given, or (strict rules) an unsensed segment with several given
        branches below it; the message names the segment.
    """
    given = set(given)
    depth = _depths(skel)
    rules = {}
    for i, name in enumerate(skel.names):
        if name in given:
            continue
        a = skel.parents[i]
        while a >= 0 and skel.names[a] not in given:
            a = skel.parents[a]
        if a < 0:
            raise SessionError(_SRC, name, "no orientation and no given ancestor",
                               f"an orientation for {name} or for the root {skel.names[0]}")
        below, stack = [], [c for c, p in enumerate(skel.parents) if p == i]
        while stack:                                  # first given segment on every branch below i
            c = stack.pop()
            if skel.names[c] in given:
                below.append(c)
            else:
                stack += [k for k, p in enumerate(skel.parents) if p == c]
        if len(below) > 1:
            rules[name] = ("ambiguous", skel.names[a], sorted(skel.names[c] for c in below))
        elif below:
            d = below[0]
            rules[name] = (skel.names[a], skel.names[d], (depth[i] - depth[a]) / (depth[d] - depth[a]))
        else:
            rules[name] = (skel.names[a], skel.names[a], 0.0)
    return rules


def fill_unsensed(skel: Skeleton, n_quat_sensed: dict, strict: bool = True) -> np.ndarray:
    """All segment orientations from the given ones, ties (K2) for the others.

    Args:
        skel: the skeleton.
        n_quat_sensed: segment name → (T, 4) segment → n quaternions (the root at least).
        strict: an unsensed segment with several given branches below it raises (True) or turns with its
            nearest given ancestor (False: the estimator's output, which must not fail).
    Returns:
        (T, S, 4) in `skel.names` order.
    Raises:
        SessionError: inconsistent shapes, the root missing, or (strict) a segment without a rule —
        each message names the segment.
    """
    shapes = {np.shape(q) for q in n_quat_sensed.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2 or next(iter(shapes))[1] != 4:
        raise SessionError(_SRC, "n_quat_sensed", f"shapes {sorted(shapes)}", "(T, 4) arrays of one length T")
    T = next(iter(shapes))[0]
    rules = tie_rules(skel, [n for n in n_quat_sensed if n in skel.names])
    out = np.empty((T, len(skel.names), 4))
    for i, name in enumerate(skel.names):
        if name in n_quat_sensed:
            out[:, i] = quat_normalize(np.asarray(n_quat_sensed[name], float))
            continue
        a, b, u = rules[name]
        if a == "ambiguous":
            if strict:
                raise SessionError(_SRC, name, f"no orientation and given segments on several branches below it {u}",
                                   f"an orientation for {name} (a segment can be tied along one chain only)")
            a, b, u = b, b, 0.0
        out[:, i] = quat_slerp(np.asarray(n_quat_sensed[a], float), np.asarray(n_quat_sensed[b], float),
                               np.full(T, u))                                                   # (K2)
    return out


def from_bvh(bvh, mapping: Optional[dict] = None) -> tuple[Skeleton, dict]:
    """MVN-named skeleton of a BVH file (path or `imugraph.io.bvh.Bvh`); see `imugraph.body.bvh_map`.

    Returns:
        (Skeleton, mapping MVN segment name → BVH joint name).
    """
    from imugraph.body.bvh_map import skeleton_from_bvh

    skel, mapping, _ = skeleton_from_bvh(bvh, mapping)
    return skel, mapping


def skeleton_from_spec(spec: Optional[str], segments: Iterable[str] = LOWER_BODY,
                       data_dir: Optional[str] = None) -> Optional[Skeleton]:
    """The skeleton an option string names, restricted to `segments`; None for the reader's default.

    spec: None, "" or "nominal" → None (the caller keeps its nominal skeleton); "height:H" → `full_body(H)`
    (Winter's proportions for body height H m); "bvh:PATH" → the segment lengths and joint positions of a BVH
    file's HIERARCHY (its OFFSETs, `from_bvh`; the MOTION is not used), e.g. the subject's own dimensions as
    entered in Xsens MVN: ``bvh:gaittoolbox/xsens/S02-Trial-Walk-1.bvh``. PATH is looked up like a session path
    (`imugraph.config.find_data_path`): as given, else in the data directory (`data_dir`: --data-dir, None for
    $IMUGRAPH_DATA or ../shared/data), else a unique match of its trailing components below it.
    Raises:
        SessionError: an unknown form, an implausible height, an unreadable BVH, or a BVH without a joint
        for one of `segments` (the message names the file and the missing segments).
    """
    segments = tuple(segments)
    if spec is None or spec in ("", "nominal"):
        return None
    kind, _, arg = str(spec).partition(":")
    if kind == "height" and arg:
        try:
            h = float(arg)
        except ValueError:
            raise SessionError("--skeleton", "height", repr(arg), "a body height in m, e.g. height:1.80") from None
        return full_body(h).subset(segments)
    if kind == "bvh" and arg:
        from imugraph.config import find_data_path
        skel, _ = from_bvh(str(find_data_path(arg, data_dir, "an existing BVH file")))
        missing = [s for s in segments if s not in skel.names]
        if missing:
            raise SessionError(arg, "HIERARCHY", f"no joint for {missing}",
                               f"a skeleton with joints for {list(segments)} (CMU, Xsens MVN or imugraph names)")
        return skel.subset(segments)
    raise SessionError("--skeleton", "spec", repr(spec), "'nominal', 'height:H' or 'bvh:PATH'")
