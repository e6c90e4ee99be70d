"""BVH (Biovision Hierarchy) motion files: read, forward kinematics into the navigation frame, write.

Format: a ``HIERARCHY`` section of nested ``ROOT``/``JOINT name { OFFSET x y z  CHANNELS n ch… … }``
blocks (``End Site { OFFSET … }`` for leaves), then ``MOTION``, ``Frames: F``, ``Frame Time: dt`` and F
rows of numbers, one per channel in hierarchy order. Rotation channels are Euler angles in degrees,
applied in the order listed (intrinsic), so a joint's local rotation is

    R_local = R_c1(a1) · R_c2(a2) · R_c3(a3)        e.g. ``Zrotation Xrotation Yrotation`` → Rz·Rx·Ry   (B1)

and forward kinematics in the file's frame f is

    fR_j = fR_parent · R_local,j ;   f_p_j = f_p_parent + fR_parent · (offset_j + translation_j)      (B2)

(the root's parent is the identity at the origin; position channels add to the offset, which is zero
for roots in practice).

Frames: BVH files are y-up. Both the CMU files and the Xsens MVN export here face +z with the subject's
left along +x in their rest pose, so the navigation frame n (z up, x forward, y left; DESIGN.md) is

    n_v = C · f_v,   C = [[0,0,1],[1,0,0],[0,1,0]]  (a cyclic permutation, det +1)                 (B3)

and a joint's world rotation in n is nR_j = C · fR_j · Cᵀ: identity in the rest pose, with the joint's
axes along n's axes. Converting a joint rotation to a body-segment frame (whose rest orientation may
differ, e.g. T-pose arms) is `imugraph.body.bvh_map`'s job.

Units: CMU's scaled files are in metres, the Xsens MVN export in millimetres. `Bvh.scale_to_m` picks
the factor (1, 0.01 or 0.001) that makes the rest-pose height of the figure 0.4–3 m, unless given.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import quat_to_rotmat, rotmat_to_quat

PathLike = Union[str, Path]
C_NF = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # (B3): n_v = C_NF · f_v
_AXES = {"X": 0, "Y": 1, "Z": 2}
_CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")


def axis_rotations(axis: str, deg: np.ndarray) -> np.ndarray:
    """(…,) angles in degrees about axis 'X', 'Y' or 'Z' → (…, 3, 3) rotation matrices."""
    a = np.deg2rad(np.asarray(deg, float))
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i = _AXES[axis]
    j, k = (i + 1) % 3, (i + 2) % 3
    R[..., i, i] = 1.0
    R[..., j, j] = c
    R[..., k, k] = c
    R[..., k, j] = s
    R[..., j, k] = -s
    return R


@dataclass(frozen=True)
class Bvh:
    """A parsed BVH file.

    Attributes:
        names: (J,) joint names in file (depth-first) order; joint 0 is the root.
        parents: (J,) parent index per joint, -1 for the root.
        offsets: (J, 3) offset of each joint from its parent, file frame and units.
        channels: (J,) tuple of channel names per joint (e.g. ('Zrotation', 'Xrotation', 'Yrotation')).
        end_sites: joint index → (3,) End Site offset in that joint's frame (file units).
        frame_time: seconds per frame.
        frames: (F, C) channel values (degrees for rotations, file units for positions).
        source: the file (for error messages).
    """

    names: tuple
    parents: tuple
    offsets: np.ndarray
    channels: tuple
    end_sites: dict
    frame_time: float
    frames: np.ndarray
    source: str = "<memory>"
    meta: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    def index(self, name: str) -> int:
        """Joint index of `name` (SessionError when absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise SessionError(self.source, "joint", repr(name), f"one of {list(self.names)}") from None

    def channel_start(self) -> np.ndarray:
        """(J,) first column of each joint's channels in `frames`."""
        return np.concatenate([[0], np.cumsum([len(c) for c in self.channels])[:-1]]).astype(int)

    def rest_positions(self) -> tuple[np.ndarray, dict]:
        """Rest-pose (all channels zero) joint positions (J, 3) and End Site positions {j: (3,)}, file frame/units."""
        pos = np.zeros((len(self.names), 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        ends = {j: pos[j] + e for j, e in self.end_sites.items()}
        return pos, ends

    def scale_to_m(self) -> float:
        """Metres per file unit: 1, 0.01 or 0.001, whichever makes the rest figure 0.4–3 m tall."""
        pos, ends = self.rest_positions()
        pts = np.vstack([pos] + [e[None] for e in ends.values()])
        height = float(np.ptp(pts[:, 1]))
        for scale in (1.0, 0.01, 0.001):
            if 0.4 <= height * scale <= 3.0:
                return scale
        raise SessionError(self.source, "OFFSET", f"a rest-pose height of {height:g} file units",
                           "a figure 0.4–3 m tall in m, cm or mm (pass units_m explicitly)")

    def local_rotations(self) -> np.ndarray:
        """(F, J, 3, 3) local joint rotations in the file frame, eq. (B1)."""
        F, J = self.n_frames, len(self.names)
        R = np.tile(np.eye(3), (F, J, 1, 1))
        for j, (chans, c0) in enumerate(zip(self.channels, self.channel_start())):
            for k, ch in enumerate(chans):
                if ch.endswith("rotation"):
                    R[:, j] = R[:, j] @ axis_rotations(ch[0], self.frames[:, c0 + k])
        return R

    def translations(self) -> np.ndarray:
        """(F, J, 3) position-channel values (zero where a joint has none), file units."""
        F, J = self.n_frames, len(self.names)
        out = np.zeros((F, J, 3))
        for j, (chans, c0) in enumerate(zip(self.channels, self.channel_start())):
            for k, ch in enumerate(chans):
                if ch.endswith("position"):
                    out[:, j, _AXES[ch[0]]] = self.frames[:, c0 + k]
        return out

    def world_poses(self, units_m: Optional[float] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward kinematics (B2) of every joint, in the navigation frame (B3).

        Args:
            units_m: metres per file unit; None detects it (`scale_to_m`).
        Returns:
            t (F,) s from 0; n_quat (F, J, 4) joint→n rotations w,x,y,z (identity at rest);
            n_pos (F, J, 3) joint positions in n, m.
        """
        scale = self.scale_to_m() if units_m is None else float(units_m)
        R_loc = self.local_rotations()
        trans = self.translations()
        F, J = self.n_frames, len(self.names)
        fR = np.empty((F, J, 3, 3))
        fp = np.empty((F, J, 3))
        for j, p in enumerate(self.parents):
            local = self.offsets[j] + trans[:, j]
            if p < 0:
                fR[:, j], fp[:, j] = R_loc[:, j], local
            else:
                fR[:, j] = fR[:, p] @ R_loc[:, j]                                   # (B2)
                fp[:, j] = fp[:, p] + np.einsum("fab,fb->fa", fR[:, p], local)
        nR = C_NF @ fR @ C_NF.T                                                     # (B3)
        n_pos = scale * fp @ C_NF.T
        t = np.arange(F) * self.frame_time
        return t, rotmat_to_quat(nR), n_pos


class _Tokens:
    """Whitespace tokens of the hierarchy with their line numbers, for error messages."""

    def __init__(self, src: str, lines: list[str]):
        self.src = src
        self.items = [(tok, n + 1) for n, line in enumerate(lines) for tok in line.split()]
        self.i = 0

    def next(self, expected: str) -> tuple[str, int]:
        if self.i >= len(self.items):
            last = self.items[-1][1] if self.items else 0
            raise SessionError(self.src, f"line {last}", "end of file", expected)
        tok = self.items[self.i]
        self.i += 1
        return tok

    def expect(self, word: str) -> None:
        tok, line = self.next(repr(word))
        if tok.rstrip(":").lower() != word.rstrip(":").lower():
            raise SessionError(self.src, f"line {line}", repr(tok), repr(word))

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            return float(tok)
        except ValueError:
            raise SessionError(self.src, f"line {line}", repr(tok), what) from None


def _parse_joint(tk: _Tokens, name: str, parent: int, out: dict) -> None:
    """Parse `{ OFFSET … CHANNELS … children }` of joint `name` (recursive)."""
    j = len(out["names"])
    out["names"].append(name)
    out["parents"].append(parent)
    tk.expect("{")
    tk.expect("OFFSET")
    out["offsets"].append([tk.number("an OFFSET number") for _ in range(3)])
    tk.expect("CHANNELS")
    tok, line = tk.next("a channel count")
    if not tok.isdigit():
        raise SessionError(tk.src, f"line {line}", repr(tok), "a channel count")
    chans = []
    for _ in range(int(tok)):
        ch, line = tk.next("a channel name")
        if ch not in _CHANNELS:
            raise SessionError(tk.src, f"line {line}", repr(ch), f"one of {_CHANNELS}")
        chans.append(ch)
    out["channels"].append(tuple(chans))
    while True:
        tok, line = tk.next("JOINT, End Site or '}'")
        if tok == "}":
            return
        if tok == "JOINT":
            child, _ = tk.next("a joint name")
            _parse_joint(tk, child, j, out)
        elif tok == "End":
            tk.expect("Site")
            tk.expect("{")
            tk.expect("OFFSET")
            out["end_sites"][j] = np.array([tk.number("an End Site number") for _ in range(3)])
            tk.expect("}")
        else:
            raise SessionError(tk.src, f"line {line}", repr(tok), "JOINT, End Site or '}'")


def read_bvh(path: PathLike) -> Bvh:
    """Parse a BVH file.

    Args:
        path: the .bvh file.
    Returns:
        Bvh.
    Raises:
        SessionError: missing file, malformed hierarchy (line named), wrong number of values per frame,
        non-numeric values, non-positive frame time.
    """
    src = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise SessionError(src, "file", f"unreadable ({exc.strerror or exc})", "a readable BVH file") from None
    lines = text.splitlines()
    motion = next((i for i, ln in enumerate(lines) if ln.strip().upper() == "MOTION"), None)
    if motion is None:
        raise SessionError(src, "MOTION", "no MOTION line", "a HIERARCHY section followed by MOTION")
    tk = _Tokens(src, lines[:motion])
    tk.expect("HIERARCHY")
    tk.expect("ROOT")
    root, _ = tk.next("the root joint name")
    out: dict = {"names": [], "parents": [], "offsets": [], "channels": [], "end_sites": {}}
    _parse_joint(tk, root, -1, out)
    if tk.i != len(tk.items):
        tok, line = tk.items[tk.i]
        raise SessionError(src, f"line {line}", repr(tok), "MOTION after the root joint's closing '}'")
    head = _Tokens(src, lines[motion + 1:motion + 3])
    head.items = [(tok, n + motion + 1) for tok, n in head.items]
    head.expect("Frames:")
    n_frames = head.number("the number of frames")
    head.expect("Frame")
    head.expect("Time:")
    frame_time = head.number("the frame time in s")
    if not frame_time > 0:
        raise SessionError(src, f"line {motion + 3}", f"Frame Time {frame_time}", "a positive frame time (s)")
    n_chan = sum(len(c) for c in out["channels"])
    rows = [ln for ln in lines[motion + 3:] if ln.strip()]
    try:
        frames = np.loadtxt(io.StringIO("\n".join(rows)), ndmin=2) if rows else np.zeros((0, n_chan))
    except ValueError as exc:
        raise SessionError(src, "MOTION", f"a non-numeric or ragged frame row ({str(exc)[:80]})",
                           f"{n_chan} numbers per frame") from None
    if frames.shape[1] != n_chan or frames.shape[0] != int(n_frames):
        raise SessionError(src, "MOTION", f"{frames.shape[0]} frames × {frames.shape[1]} values",
                           f"{int(n_frames)} frames × {n_chan} values (Frames: and CHANNELS)")
    if not np.all(np.isfinite(frames)):
        bad = int(np.argwhere(~np.isfinite(frames))[0, 0])
        raise SessionError(src, f"frame {bad}", "NaN or infinite values", "finite channel values")
    return Bvh(names=tuple(out["names"]), parents=tuple(out["parents"]), offsets=np.array(out["offsets"], float),
               channels=tuple(out["channels"]), end_sites=out["end_sites"], frame_time=float(frame_time),
               frames=frames, source=src)


def zxy_from_rotmat(R: np.ndarray) -> np.ndarray:
    """(…, 3, 3) → (…, 3) degrees (a, b, c) with R = Rz(a)·Rx(b)·Ry(c).

    From the product: R[2,1] = sin b, R[0,1] = −sin a cos b, R[1,1] = cos a cos b,
    R[2,0] = −cos b sin c, R[2,2] = cos b cos c.
    """
    b = np.arcsin(np.clip(R[..., 2, 1], -1.0, 1.0))
    a = np.arctan2(-R[..., 0, 1], R[..., 1, 1])
    c = np.arctan2(-R[..., 2, 0], R[..., 2, 2])
    return np.rad2deg(np.stack([a, b, c], -1))


def write_bvh(path: PathLike, skel, t: np.ndarray, n_quat: np.ndarray, n_root: np.ndarray,
              units_m: float = 1.0) -> Path:
    """Write a BVH of `skel` (an `imugraph.body.skeleton.Skeleton`) whose rest pose is its neutral pose.

    Joints are the skeleton's segments (MVN names), each with the segment's offset (B3 inverted) and
    ``Zrotation Xrotation Yrotation`` channels; the root also has ``Xposition Yposition Zposition``.
    Leaves get an End Site at the segment's distal end. Reading the file back and converting with
    `imugraph.body.skeleton.from_bvh` gives the same segment orientations and origins.

    Args:
        path: target .bvh (written atomically).
        skel: the Skeleton.
        t: (T,) s, uniformly spaced (the frame time is their median step; 1/60 s when T = 1).
        n_quat: (T, S, 4) segment → n, w,x,y,z.
        n_root: (T, 3) root origin in n, m.
        units_m: metres per written unit (1: metres, 0.01: cm).
    Returns:
        The target path.
    Raises:
        ValueError: shapes that do not match the skeleton (a programming error).
    """
    from imugraph.io.writers import atomic_write_text

    t = np.asarray(t, float).reshape(-1)
    S, T = len(skel.names), t.size
    n_quat, n_root = np.asarray(n_quat, float), np.asarray(n_root, float)
    if n_quat.shape != (T, S, 4) or n_root.shape != (T, 3):
        raise ValueError(f"write_bvh: n_quat {n_quat.shape}, n_root {n_root.shape}; expected ({T}, {S}, 4), ({T}, 3)")
    nR = quat_to_rotmat(n_quat)
    par = np.array(skel.parents)
    local = nR.copy()
    for i in range(1, S):
        local[:, i] = np.swapaxes(nR[:, par[i]], -1, -2) @ nR[:, i]
    angles = zxy_from_rotmat(C_NF.T @ local @ C_NF)                 # (B3) inverted: file-frame local rotations
    f_root = n_root @ C_NF / units_m
    lines = ["HIERARCHY"]

    def emit(i: int, depth: int) -> None:
        pad = "\t" * depth
        off = C_NF.T @ skel.offsets[i] / units_m
        lines.append(f"{pad}{'ROOT' if i == 0 else 'JOINT'} {skel.names[i]}")
        lines.append(pad + "{")
        lines.append(f"{pad}\tOFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        pos = "Xposition Yposition Zposition " if i == 0 else ""
        lines.append(f"{pad}\tCHANNELS {6 if i == 0 else 3} {pos}Zrotation Xrotation Yrotation")
        kids = [k for k in range(S) if par[k] == i]
        for k in kids:
            emit(k, depth + 1)
        if not kids:
            end = C_NF.T @ skel.ends[i] / units_m
            lines.extend([f"{pad}\tEnd Site", pad + "\t{", f"{pad}\t\tOFFSET {end[0]:.6f} {end[1]:.6f} {end[2]:.6f}",
                          pad + "\t}"])
        lines.append(pad + "}")

    emit(0, 0)
    dt = float(np.median(np.diff(t))) if T > 1 else 1.0 / 60.0
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {dt:.9f}"]
    cols = np.concatenate([f_root, angles.reshape(T, -1)], axis=1)
    body = "\n".join(" ".join(f"{v:.6f}" for v in row) for row in cols)
    return atomic_write_text(path, "\n".join(lines) + "\n" + body + ("\n" if T else ""))
