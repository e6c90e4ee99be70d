"""Repair of physically impossible joint rotations in motion-capture data (before any filtering).

Optical mocap files hold glitches: a marker swap or a solver flip turns a joint by tens of degrees in
one or a few frames and back. CMU 131_01's right wrist turns ≈ 60° within one 1/120 s frame (> 100 rad/s)
and its upper arm spins ≈ 70° about its long axis in 7 frames (up to 35 rad/s); a gyroscope on such a
segment would read 50–60 rad/s, which no body segment in gait or dance does.

Test, per joint (the rotation of a segment relative to its parent, r = nR_parentᵀ nR_child; the root's
world rotation) and per frame interval k:

    ω_k = θ(r_k, r_{k+1}) / (t_{k+1} − t_k),   θ(a, b) = 2 arccos |⟨a, b⟩|   (quaternion angle)      (G1)

An interval with ω_k > max_rate is impossible. Limit: `MAX_JOINT_RATE` = 25 rad/s (≈ 1430 °/s). Segment
rates in walking stay below ≈ 10 rad/s (the shank's swing-phase peak is the largest, a few rad/s), fast
everyday and dance arm movements below ≈ 20 rad/s; only ballistic sport motions exceed this (a pitcher's
shoulder internal rotation, ~100 rad/s), so the limit suits gait/dance data such as CMU 131 and is an
argument (None disables the repair) for anything else.

Repair of a run of consecutive impossible intervals [k0, k1]: the frames strictly between the anchors
a = k0 and b = k1 + 1 are replaced by the geodesic between the anchors' joint rotations,

    r_i = slerp(r_a, r_b, (t_i − t_a)/(t_b − t_a)),   a < i < b,                                      (G2)

whose rate θ(r_a, r_b)/(t_b − t_a) is constant; while that exceeds max_rate the anchors move one frame
outwards on both sides (a spike that returns, or a step that stays, is spread over more frames), up to
`max_gap_s`; runs that still cannot be brought under the limit are left as they are and reported.
World rotations are recomposed along the tree (nR_child = nR_parent r_child), so a repaired joint moves its
descendants with it and every other joint keeps its own rotation.
"""

from __future__ import annotations

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import quat_angle, quat_conj, quat_mul, quat_normalize, quat_slerp

MAX_JOINT_RATE = 25.0          # rad/s, module docstring
_SRC = "<imugraph.body.repair>"


def joint_rotations(parents, n_quat: np.ndarray) -> np.ndarray:
    """(F, S, 4) r: each segment relative to its parent (root: its world rotation)."""
    r = np.array(n_quat, float)
    for i, p in enumerate(parents):
        if p >= 0:
            r[:, i] = quat_mul(quat_conj(n_quat[:, p]), n_quat[:, i])
    return r


def compose(parents, r: np.ndarray) -> np.ndarray:
    """Inverse of `joint_rotations`: world rotations nR_i = nR_parent(i) r_i (parents before children)."""
    q = np.array(r, float)
    for i, p in enumerate(parents):
        if p >= 0:
            q[:, i] = quat_mul(q[:, p], r[:, i])
    return quat_normalize(q)


def joint_rates(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(F−1, S) frame-to-frame joint rates ω_k, rad/s (G1)."""
    return quat_angle(r[:-1], r[1:]) / np.diff(t)[:, None]


def _repair_one(t: np.ndarray, r: np.ndarray, max_rate: float, max_gap_s: float) -> tuple[np.ndarray, int, int]:
    """One joint's (F, 4) rotations with its impossible runs repaired: (r, frames replaced, runs left)."""
    r = np.array(r, float)
    F = r.shape[0]
    replaced = np.zeros(F, bool)
    skipped = set()
    while True:
        w = quat_angle(r[:-1], r[1:]) / np.diff(t)
        bad = np.flatnonzero(w > max_rate * (1 + 1e-9))
        bad = [k for k in bad if k not in skipped]
        if not bad:
            break
        k0 = k1 = bad[0]
        while k1 + 1 < F - 1 and w[k1 + 1] > max_rate * (1 + 1e-9):
            k1 += 1
        a, b = k0, k1 + 1
        while True:
            if quat_angle(r[a], r[b]) / (t[b] - t[a]) <= max_rate or t[b] - t[a] > max_gap_s or (a == 0 and b == F - 1):
                break
            a, b = max(a - 1, 0), min(b + 1, F - 1)
        if quat_angle(r[a], r[b]) / (t[b] - t[a]) > max_rate or b - a < 2:
            skipped.update(range(k0, k1 + 1))                                  # cannot repair: leave, report
            continue
        i = np.arange(a + 1, b)
        u = (t[i] - t[a]) / (t[b] - t[a])
        r[i] = quat_slerp(np.broadcast_to(r[a], (i.size, 4)), np.broadcast_to(r[b], (i.size, 4)), u)   # (G2)
        replaced[i] = True
    runs = 0
    if skipped:
        s = np.array(sorted(skipped))
        runs = int(1 + np.sum(np.diff(s) > 1))
    return r, int(replaced.sum()), runs


def repair_glitches(parents, names, t: np.ndarray, n_quat: np.ndarray, max_rate: float = MAX_JOINT_RATE,
                    max_gap_s: float = 0.25) -> tuple[np.ndarray, dict]:
    """World segment rotations with impossible joint rotations repaired (module docstring).

    Args:
        parents: (S,) parent index per segment (−1 for the root), parents before children.
        names: (S,) segment names (for the report).
        t: (F,) frame times, s, strictly increasing.
        n_quat: (F, S, 4) segment → n rotations (w, x, y, z).
        max_rate: joint rate limit, rad/s (G1).
        max_gap_s: longest stretch one repair may replace, s.
    Returns:
        (n_quat repaired (F, S, 4), report) with report = {"max_rate": …, "frames": {segment: frames
        replaced}, "unrepaired_runs": {segment: runs}, "frames_total": distinct frames touched,
        "max_rate_before"/"max_rate_after": {segment: rad/s} for the segments that exceeded the limit}.
    Raises:
        SessionError: inconsistent shapes or non-increasing times.
    """
    t, n_quat = np.asarray(t, float), quat_normalize(np.asarray(n_quat, float))
    S = len(parents)
    if n_quat.ndim != 3 or n_quat.shape[1:] != (S, 4) or t.shape != (n_quat.shape[0],) or np.any(np.diff(t) <= 0):
        raise SessionError(_SRC, "n_quat/t", f"{n_quat.shape}, t {t.shape}", f"(F, {S}, 4) and increasing (F,) times")
    r = joint_rotations(parents, n_quat)
    before = joint_rates(t, r).max(axis=0) if t.size > 1 else np.zeros(S)
    frames, left, touched = {}, {}, np.zeros(t.size, bool)
    for i in np.flatnonzero(before > max_rate):
        r_new, n, runs = _repair_one(t, r[:, i], max_rate, max_gap_s)
        touched |= np.any(np.abs(r_new - r[:, i]) > 0, axis=1)
        r[:, i] = r_new
        frames[names[i]] = n
        if runs:
            left[names[i]] = runs
    after = joint_rates(t, r).max(axis=0) if t.size > 1 else np.zeros(S)
    out = compose(parents, r) if frames else n_quat
    hit = [names[i] for i in np.flatnonzero(before > max_rate)]
    report = {"max_rate": float(max_rate), "frames": frames, "unrepaired_runs": left,
              "frames_total": int(touched.sum()),
              "max_rate_before": {n: float(before[names.index(n)]) for n in hit},
              "max_rate_after": {n: float(after[names.index(n)]) for n in hit}}
    return out, report
