"""Figures of body motion: joint angles over time and stick-figure snapshots (matplotlib, Agg, atomic PNG).

`plot_joint_angles`: one panel per joint (right and left side by side), flexion/abduction/rotation as three
coloured lines (degrees), an optional reference (truth or another system) dashed in the same colours.

`plot_stick_figures`: snapshots of the skeleton at chosen times, each drawn in the body's own heading frame
(rotated about z by −ψ, ψ the pelvis heading at that instant) so the sagittal view (forward x, up z) and
the frontal view (left y, up z) are comparable along a walk: a segment is drawn from its origin p_i to its
distal end p_i + nRb_i · end_i. Right-side segments red, left blue, the midline black (a key below the
panels); unsensed segments are drawn thinner.

Both write through `imugraph.io.figures.save_figure_atomic` (temporary file + os.replace).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
from matplotlib.figure import Figure

from imugraph.body.angles import COLUMNS
from imugraph.errors import SessionError
from imugraph.geometry import quat_to_rotmat
from imugraph.io.figures import save_figure_atomic

_COL = ("tab:red", "tab:green", "tab:blue")
_SIDE = {"Right": "tab:red", "Left": "tab:blue", "": "k"}      # stick figures: segment colour by side


def _joint_grid(joints: Sequence[str]) -> list[list[Optional[str]]]:
    """Rows of [right, left] joint names (or [name, None] for unpaired joints)."""
    rows, seen = [], set()
    for j in joints:
        if j in seen:
            continue
        if j.startswith("Right") and "Left" + j[5:] in joints:
            rows.append([j, "Left" + j[5:]])
            seen.update(rows[-1])
        elif j.startswith("Left") and "Right" + j[4:] in joints:
            rows.append(["Right" + j[4:], j])
            seen.update(rows[-1])
        else:
            rows.append([j, None])
            seen.add(j)
    return rows


def plot_joint_angles(path, t: np.ndarray, angles: dict, reference: Optional[dict] = None,
                      title: str = "Joint angles", ref_label: str = "reference") -> Figure:
    """Joint angles over time (degrees), optionally over a reference; PNG written atomically.

    Args:
        path: target .png.
        t: (T,) s.
        angles: {joint: (T, 3) degrees (flexion, abduction, rotation)}.
        reference: {joint: (T_r, 3)} on the same t (T_r = T) or None.
        title: figure title.
        ref_label: legend name of the reference.
    Returns:
        The Figure.
    Raises:
        SessionError: no joints, or an array that is not (T, 3).
    """
    t = np.asarray(t, float).reshape(-1)
    if not angles:
        raise SessionError(str(path), "angles", "no joints", "at least one joint")
    for j, a in list(angles.items()) + list((reference or {}).items()):
        if np.shape(a) != (t.size, 3):
            raise SessionError(str(path), j, f"shape {np.shape(a)}", f"({t.size}, 3) degrees")
    rows = _joint_grid(list(angles))
    fig = Figure(figsize=(11, 1.9 * len(rows) + 0.8))
    axes = fig.subplots(len(rows), 2, squeeze=False, sharex=True)
    for r, pair in enumerate(rows):
        for c, joint in enumerate(pair):
            ax = axes[r, c]
            if joint is None:
                ax.set_visible(False)
                continue
            for k, name in enumerate(COLUMNS):
                ax.plot(t, angles[joint][:, k], color=_COL[k], lw=1.0, label=name)
                if reference is not None and joint in reference:
                    ax.plot(t, reference[joint][:, k], color=_COL[k], lw=0.8, ls="--",
                            label=f"{name} ({ref_label})" if r == 0 else None)
            ax.set_ylabel(f"{joint} (°)", fontsize=8)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7, ncol=2, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    fig.suptitle(title)
    fig.tight_layout()
    save_figure_atomic(fig, path)
    return fig


def _heading(R: np.ndarray) -> float:
    x = R[:, 0]
    return float(np.arctan2(x[1], x[0]))


def plot_stick_figures(path, skel, t: np.ndarray, n_quat: np.ndarray, n_pos: np.ndarray,
                       times: Optional[Sequence[float]] = None, count: int = 6,
                       title: str = "Stick figures") -> Figure:
    """Skeleton snapshots, sagittal (top row) and frontal (bottom row) views in the body's heading frame.

    Args:
        path: target .png.
        skel: the skeleton (names, parents, ends, sensed).
        t: (T,) s.
        n_quat: (T, S, 4) segment → n.
        n_pos: (T, S, 3) segment origins, m.
        times: snapshot times, s (default `count` evenly spaced over t).
        count: number of snapshots when `times` is None.
        title: figure title.
    Returns:
        The Figure.
    Raises:
        SessionError: inconsistent shapes.
    """
    t = np.asarray(t, float).reshape(-1)
    S = len(skel.names)
    if np.shape(n_quat) != (t.size, S, 4) or np.shape(n_pos) != (t.size, S, 3):
        raise SessionError(str(path), "n_quat/n_pos", f"{np.shape(n_quat)}, {np.shape(n_pos)}",
                           f"({t.size}, {S}, 4) and ({t.size}, {S}, 3)")
    if times is None:
        times = np.linspace(t[0], t[-1], max(1, int(count)))
    ks = [int(np.argmin(np.abs(t - tk))) for tk in times]
    ends = np.asarray(skel.ends, float)
    snaps = []
    for k in ks:
        R = quat_to_rotmat(np.asarray(n_quat[k], float))
        psi = _heading(R[0])
        Rh = np.array([[np.cos(psi), np.sin(psi), 0.0], [-np.sin(psi), np.cos(psi), 0.0], [0.0, 0.0, 1.0]])
        p0 = (np.asarray(n_pos[k], float) - n_pos[k][0]) @ Rh.T          # pelvis-centred, heading removed
        p1 = p0 + np.einsum("ab,sbc,sc->sa", Rh, R, ends)                 # distal ends
        snaps.append((k, p0, p1))
    allp = np.concatenate([np.vstack([a, b]) for _, a, b in snaps])
    z_lo, z_hi = float(np.nanmin(allp[:, 2])) - 0.05, float(np.nanmax(allp[:, 2])) + 0.05
    half = max(0.35 * (z_hi - z_lo), float(np.nanmax(np.abs(allp[:, :2]))) + 0.05)
    panel_h = 2.0 * (z_hi - z_lo) / (2 * half)
    fig = Figure(figsize=(2.0 * len(ks) + 0.6, 2 * panel_h + 1.2))
    axes = fig.subplots(2, len(ks), squeeze=False)
    for c, (k, p0, p1) in enumerate(snaps):
        for r, (h, label) in enumerate(((0, "forward x (m)"), (1, "left y (m)"))):
            ax = axes[r, c]
            for i, name in enumerate(skel.names):
                lw = 2.2 if name in skel.sensed else 1.0
                colour = _SIDE["Right" if name.startswith("Right") else "Left" if name.startswith("Left") else ""]
                ax.plot([p0[i, h], p1[i, h]], [p0[i, 2], p1[i, 2]], color=colour, lw=lw)
                par = skel.parents[i]
                if par >= 0:                      # link from the parent's frame to the joint (offset)
                    ax.plot([p0[par, h], p0[i, h]], [p0[par, 2], p0[i, 2]], color="0.6", lw=0.6)
            ax.set_aspect("equal")
            ax.set_xlim(-half, half)
            ax.set_ylim(z_lo, z_hi)
            ax.tick_params(labelsize=6)
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"t = {t[k]:.2f} s", fontsize=8)
            if c == 0:
                ax.set_ylabel(f"up z (m)\n{'sagittal' if r == 0 else 'frontal'}", fontsize=7)
            ax.set_xlabel(label, fontsize=6)
    fig.suptitle(title)
    # colour key (U23 defect 14: which side is which was nowhere on the figure)
    fig.legend(handles=_stick_key(), loc="lower center", ncol=5, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
    save_figure_atomic(fig, path)
    return fig


def _stick_key() -> list:
    """Legend handles of `plot_stick_figures`: the side colours, the parent-to-joint links, sensed vs not."""
    from matplotlib.lines import Line2D

    return [Line2D([], [], color=_SIDE["Right"], lw=2.2, label="right side"),
            Line2D([], [], color=_SIDE["Left"], lw=2.2, label="left side"),
            Line2D([], [], color=_SIDE[""], lw=2.2, label="midline"),
            Line2D([], [], color="0.6", lw=0.6, label="link to joint"),
            Line2D([], [], color=_SIDE[""], lw=1.0, label="thin: no sensor")]
