"""Joint angles, ISB-style (Grood & Suntay 1983; Wu et al., J. Biomech. 35 (2002) 543 and 38 (2005) 981).

A joint's rotation is the distal segment's orientation in the proximal segment's frame,

    pRd = nR_pᵀ · nR_d            (identity in the neutral N-pose, where all segment frames align)    (A1)

decomposed as the Cardan sequence of the joint coordinate system — flexion/extension about the
proximal segment's lateral axis, abduction/adduction about the floating (anterior) axis, internal/
external rotation about the distal segment's long axis. With MVN segment axes (x anterior, y left,
z up) that is

    pRd = Ry(α) · Rx(β) · Rz(γ)
    β = asin(−R[1,2]),  α = atan2(R[0,2], R[2,2]),  γ = atan2(R[1,0], R[1,1])                     (A2)

(ISB's ZXY sequence with its z = medio-lateral, x = anterior, y = long axes renamed to MVN's y, x, z).
Reported angles, in degrees, with signs chosen so that the clinical direction is positive:

- flexion = s_flex · α: Ry(α) with α > 0 swings a downward long axis backwards, so s_flex = −1 for the
  hip, shoulder and elbow (segment forward = flexion), +1 for the knee (shank backwards = flexion),
  −1 for the ankle (dorsiflexion positive: toes up), +1 for the trunk and neck (bending forward);
- abduction = β on the left side, −β on the right (distal segment away from the midline positive;
  for the knee this is valgus, for the ankle eversion-like tilt);
- rotation = γ on the right side, −γ on the left (internal rotation positive: the front of the distal
  segment turning towards the midline).
"""

from __future__ import annotations

from pathlib import Path
from typing import Union

import numpy as np

from imugraph.body.skeleton import Skeleton
from imugraph.errors import SessionError
from imugraph.geometry import quat_to_rotmat
from imugraph.io.writers import atomic_write_text

# joint name -> (proximal segment, distal segment)
JOINTS = {}
for _side in ("Right", "Left"):
    JOINTS.update({f"{_side}Hip": ("Pelvis", f"{_side}UpperLeg"),
                   f"{_side}Knee": (f"{_side}UpperLeg", f"{_side}LowerLeg"),
                   f"{_side}Ankle": (f"{_side}LowerLeg", f"{_side}Foot"),
                   f"{_side}Shoulder": (f"{_side}Shoulder", f"{_side}UpperArm"),
                   f"{_side}Elbow": (f"{_side}UpperArm", f"{_side}ForeArm")})
JOINTS.update({"Trunk": ("Pelvis", "T8"), "Neck": ("T8", "Head")})
FLEXION_SIGN = {"Hip": -1.0, "Knee": 1.0, "Ankle": -1.0, "Shoulder": -1.0, "Elbow": -1.0, "Trunk": 1.0, "Neck": 1.0}
COLUMNS = ("flexion", "abduction", "rotation")


def cardan_yxz(R: np.ndarray) -> np.ndarray:
    """(…, 3, 3) → (…, 3) radians (α, β, γ) with R = Ry(α)·Rx(β)·Rz(γ), eq. (A2)."""
    beta = np.arcsin(np.clip(-R[..., 1, 2], -1.0, 1.0))
    alpha = np.arctan2(R[..., 0, 2], R[..., 2, 2])
    gamma = np.arctan2(R[..., 1, 0], R[..., 1, 1])
    return np.stack([alpha, beta, gamma], -1)


def _signs(joint: str) -> np.ndarray:
    kind = joint.replace("Right", "").replace("Left", "")
    side = -1.0 if joint.startswith("Right") else 1.0
    return np.array([FLEXION_SIGN[kind], side, -side])


def joint_angles(skel: Skeleton, n_quat: np.ndarray) -> dict:
    """Flexion, abduction, rotation of every joint of `JOINTS` whose two segments are in `skel`.

    Args:
        skel: the skeleton (segment order of n_quat).
        n_quat: (T, S, 4) segment → n rotations w,x,y,z.
    Returns:
        {joint name: (T, 3) degrees, columns (flexion, abduction, rotation)} in `JOINTS` order.
    Raises:
        SessionError: n_quat not (T, S, 4).
    """
    n_quat = np.asarray(n_quat, float)
    if n_quat.ndim != 3 or n_quat.shape[1:] != (len(skel.names), 4):
        raise SessionError("<imugraph.body.angles>", "n_quat", f"shape {n_quat.shape}",
                           f"(T, {len(skel.names)}, 4) for the skeleton's segments")
    nR = quat_to_rotmat(n_quat)
    out = {}
    for joint, (prox, dist) in JOINTS.items():
        if prox in skel.names and dist in skel.names:
            R = np.swapaxes(nR[:, skel.index(prox)], -1, -2) @ nR[:, skel.index(dist)]       # (A1)
            out[joint] = np.rad2deg(cardan_yxz(R)) * _signs(joint)                          # (A2) + signs
    return out


def write_joint_angles_csv(path: Union[str, Path], t: np.ndarray, angles: dict) -> Path:
    """``joint_angles.csv``: header ``t,<Joint>_flexion,<Joint>_abduction,<Joint>_rotation,…`` (degrees), atomic.

    Args:
        path: target file.
        t: (T,) s.
        angles: {joint: (T, 3) degrees} as from `joint_angles`.
    Returns:
        The target path.
    Raises:
        ValueError: an angle array that is not (T, 3) (a programming error).
    """
    t = np.asarray(t, float).reshape(-1)
    cols, data = ["t"], [t[:, None]]
    for joint, a in angles.items():
        a = np.asarray(a, float)
        if a.shape != (t.size, 3):
            raise ValueError(f"joint_angles: {joint} has shape {a.shape}, expected ({t.size}, 3)")
        cols += [f"{joint}_{c}" for c in COLUMNS]
        data.append(a)
    table = np.hstack(data)
    lines = [",".join(cols)] + [",".join(f"{v:.6g}" for v in row) for row in table]
    return atomic_write_text(path, "\n".join(lines) + "\n")
