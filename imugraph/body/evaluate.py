"""Scoring body motion: joint angles, relative segment positions, and the gaittoolbox Vicon comparison.

Joint-angle error (against a truth on the same skeleton). Angles a(t) from `imugraph.body.angles` (degrees,
columns flexion, abduction, rotation); the error is wrapped into (−180°, 180°],

    e_j,c(t) = wrap(a_est,j,c(t) − a_ref,j,c(t)),   RMSE_j,c = sqrt(mean_t e²),   RMSE_j = sqrt(mean_c RMSE_j,c²)   (E1)

plus a geodesic column, the total rotation angle between the two joint rotations pRd (angles.py (A1)),
free of the Cardan singularity at |abduction| → 90° (shoulders), where (E1)'s flexion/rotation blow up:

    g_j(t) = |Log(pRd_ref(t)ᵀ · pRd_est(t))|,   RMSE_j,geodesic = sqrt(mean_t g²)                      (E1g)

Relative segment position error. Segment origins relative to the root (Pelvis), r_i(t) = p_i(t) − p_root(t),
compared after the constant heading offset ψ about z that fits them best (an estimator without magnetometers
fixes its heading arbitrarily — the gauge — so only a constant rotation about the vertical is removed):

    ψ = atan2(Σ a_x b_y − a_y b_x, Σ a_x b_x + a_y b_y)   (a = r_est, b = r_ref, all i, t)            (E2)
    d_i(t) = |Rz(ψ) r_est,i(t) − r_ref,i(t)|,  RMS_i = sqrt(mean_t d_i²),  RMS = sqrt(mean_i,t d²)

Vicon comparison (gaittoolbox, `compare_with_vicon`). The Vicon segment quaternions (w,x,y,z, segment → Vicon
world) have MVN-like axes (x anterior, y left, z up = proximal) for pelvis, thighs and shanks; the feet have
x down and z forward (measured on S02-Trial-Walk-1: TOE − ankle lies along +z, vertical along −x). The
nominal fix `VICON_AXES` turns the feet into MVN axes (x forward, y left, z up): R_mvn = R_vicon · C_foot.
(The w-first, segment → world reading is confirmed by the geometry: with it the mean unit vector hip → knee
in the thigh frame and knee → ankle in the shank frame is (0.00, 0.00, −1.00), the pelvis y axis points to
the left hip.)
Two offset handlings, stated with every number:

- "offset": joint angles of the axis-fixed Vicon segments; per joint and column the mean difference over the
  scored samples is removed before the RMSE (a constant angle offset per joint and axis).
- "segment": a constant alignment per segment, R_est(t) ≈ W · R_vicon(t) · C_s (W: world alignment, C_s: the
  segment frame): W a rotation about z fixed by the pelvis x axes, C_s chordal means (`fit_segment_alignment`),
  fitted on the whole Vicon window (align_s None), or on its first `align_s` seconds with only the rest
  scored (held out).

Both also search the best integer time shift of the estimate within ±max_shift samples (the same for every
joint), since the IMU and Vicon clocks are aligned only to within a few samples: shift s compares the
estimate at IMU sample i + s with the Vicon frame of IMU sample i (s > 0: the estimate lags).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from imugraph.body.angles import COLUMNS, JOINTS, joint_angles
from imugraph.errors import SessionError
from imugraph.geometry import logmap, quat_to_rotmat, rotmat_to_quat

_SRC = "<imugraph.body.evaluate>"
LOWER_JOINTS = ("RightHip", "RightKnee", "RightAnkle", "LeftHip", "LeftKnee", "LeftAnkle")
_C_FOOT = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])     # columns: MVN x, y, z in Vicon foot axes
VICON_AXES = {"RightFoot": _C_FOOT, "LeftFoot": _C_FOOT}


def wrap_deg(a: np.ndarray) -> np.ndarray:
    """Angles in degrees wrapped into (−180, 180]."""
    return 180.0 - np.mod(180.0 - np.asarray(a, float), 360.0)


def _rmse_table(err: dict, geo: Optional[dict] = None) -> dict:
    """{joint: (T, 3) errors, deg} → {joint: {flexion, abduction, rotation, all[, geodesic]}} RMSE, eq. (E1);
    geo {joint: (T,) geodesic errors, deg} adds the (E1g) column."""
    out = {}
    for j, e in err.items():
        cols = np.sqrt(np.mean(np.square(e), axis=0)) if e.shape[0] else np.full(3, np.nan)
        out[j] = {c: float(v) for c, v in zip(COLUMNS, cols)}
        out[j]["all"] = float(np.sqrt(np.mean(np.square(cols))))
        if geo is not None and j in geo:
            g = geo[j]
            out[j]["geodesic"] = float(np.sqrt(np.mean(np.square(g)))) if g.size else float("nan")
    return out


def _joint_rotations(skel, q: np.ndarray, joints) -> dict:
    """{joint: (T, 3, 3) pRd = nR_pᵀ nR_d} (angles.py (A1)) for the joints in `joints` the skeleton has."""
    R = quat_to_rotmat(np.asarray(q, float))
    names = list(skel.names)
    return {j: np.swapaxes(R[:, names.index(p)], -1, -2) @ R[:, names.index(d)]
            for j, (p, d) in JOINTS.items() if j in joints and p in names and d in names}


def joint_geodesic_errors(skel, q_est: np.ndarray, q_ref: np.ndarray, joints=None,
                          offsets: bool = False) -> dict:
    """{joint: (T,) total rotation angle in degrees between estimated and reference joint rotations} (E1g).

    offsets True: a constant per-joint rotation offset C = proj_SO3(Σ_t E(t)), E = pRd_refᵀ pRd_est, is
    removed first (g = |Log(Cᵀ E)|), the geodesic analogue of the "offset" handling of `compare_with_vicon`.
    """
    q_est, q_ref = np.asarray(q_est, float), np.asarray(q_ref, float)
    if q_est.shape != q_ref.shape:
        raise SessionError(_SRC, "n_quat", f"estimate {q_est.shape} vs reference {q_ref.shape}", "equal shapes")
    keep = JOINTS if joints is None else joints
    Re, Rr = _joint_rotations(skel, q_est, keep), _joint_rotations(skel, q_ref, keep)
    out = {}
    for j in Re:
        E = np.swapaxes(Rr[j], -1, -2) @ Re[j]                       # pRd_refᵀ pRd_est
        if offsets and E.shape[0]:
            E = _proj_so3(E.sum(0)).T @ E
        out[j] = np.rad2deg(np.linalg.norm(logmap(E), axis=-1)) if E.shape[0] else np.zeros(0)
    return out


def _mask(mask: Optional[np.ndarray], T: int, src: str) -> np.ndarray:
    if mask is None:
        return np.ones(T, bool)
    m = np.asarray(mask, bool).reshape(-1)
    if m.size != T:
        raise SessionError(src, "mask", f"{m.size} values", f"{T} (one per sample)")
    return m


def joint_angle_errors(skel, q_est: np.ndarray, q_ref: np.ndarray, joints=None) -> dict:
    """{joint: (T, 3) wrapped angle errors in degrees} of every joint both poses define (E1)."""
    q_est, q_ref = np.asarray(q_est, float), np.asarray(q_ref, float)
    if q_est.shape != q_ref.shape:
        raise SessionError(_SRC, "n_quat", f"estimate {q_est.shape} vs reference {q_ref.shape}", "equal shapes")
    a_est, a_ref = joint_angles(skel, q_est), joint_angles(skel, q_ref)
    keep = [j for j in a_est if joints is None or j in joints]
    return {j: wrap_deg(a_est[j] - a_ref[j]) for j in keep}


def joint_angle_rmse(skel, q_est: np.ndarray, q_ref: np.ndarray, mask: Optional[np.ndarray] = None,
                     joints=None) -> dict:
    """Joint-angle RMSE per joint and column, eq. (E1).

    Args:
        skel: skeleton of both pose arrays (segment order).
        q_est, q_ref: (T, S, 4) segment → n quaternions.
        mask: (T,) samples to score (default all).
        joints: joint names to keep (default every joint of `JOINTS` the skeleton has).
    Returns:
        {joint: {"flexion", "abduction", "rotation", "all", "geodesic" (E1g)} degrees}.
    """
    m = _mask(mask, np.shape(q_est)[0], _SRC)
    geo = {j: g[m] for j, g in joint_geodesic_errors(skel, q_est, q_ref, joints).items()}
    return _rmse_table({j: e[m] for j, e in joint_angle_errors(skel, q_est, q_ref, joints).items()}, geo)


def best_heading(a: np.ndarray, b: np.ndarray) -> float:
    """ψ (rad) minimising Σ |Rz(ψ) a − b|² over (…, 3) vector pairs, eq. (E2)."""
    a, b = np.reshape(a, (-1, 3)), np.reshape(b, (-1, 3))
    ok = np.all(np.isfinite(a), 1) & np.all(np.isfinite(b), 1)
    a, b = a[ok], b[ok]
    cross = np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    dot = np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    return float(np.arctan2(cross, dot))


def rz(psi: float) -> np.ndarray:
    """Rotation about z by ψ (rad)."""
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def relative_position_error(names, pos_est: np.ndarray, pos_ref: np.ndarray, root: str = "Pelvis",
                            mask: Optional[np.ndarray] = None, align_heading: bool = True) -> dict:
    """Error of the segment origins relative to the root, eq. (E2).

    Args:
        names: (S,) segment names of both arrays.
        pos_est, pos_ref: (T, S, 3) segment origins in n, m.
        root: the reference segment.
        mask: (T,) samples to score.
        align_heading: remove the best constant heading offset (else compare as given).
    Returns:
        {"per_segment": {name: RMS m}, "rms_m": all segments and samples, "max_segment": name of the worst,
         "heading_deg": ψ removed}.
    """
    names = list(names)
    pe, pr = np.asarray(pos_est, float), np.asarray(pos_ref, float)
    if pe.shape != pr.shape or pe.ndim != 3 or pe.shape[1:] != (len(names), 3):
        raise SessionError(_SRC, "n_pos", f"estimate {pe.shape} vs reference {pr.shape}", f"(T, {len(names)}, 3) both")
    if root not in names:
        raise SessionError(_SRC, "root", repr(root), f"one of {names}")
    m = _mask(mask, pe.shape[0], _SRC)
    i0 = names.index(root)
    a = (pe - pe[:, i0:i0 + 1])[m]
    b = (pr - pr[:, i0:i0 + 1])[m]
    psi = best_heading(a, b) if align_heading else 0.0
    d = np.linalg.norm(a @ rz(psi).T - b, axis=-1)                                             # (E2)
    per = {n: float(np.sqrt(np.mean(d[:, i] ** 2))) for i, n in enumerate(names) if i != i0}
    return {"per_segment": per, "rms_m": float(np.sqrt(np.mean(np.delete(d, i0, axis=1) ** 2))),
            "max_segment": max(per, key=per.get) if per else None, "heading_deg": float(np.rad2deg(psi))}


def segment_orientation_error(names, q_est: np.ndarray, q_ref: np.ndarray, psi_rad: float = 0.0,
                              mask: Optional[np.ndarray] = None) -> dict:
    """RMS rotation angle (deg) per segment between Rz(ψ)·nRb_est and nRb_ref."""
    Re = rz(psi_rad) @ quat_to_rotmat(np.asarray(q_est, float))
    Rr = quat_to_rotmat(np.asarray(q_ref, float))
    m = _mask(mask, Re.shape[0], _SRC)
    ang = np.linalg.norm(logmap(np.swapaxes(Rr[m], -1, -2) @ Re[m]), axis=-1)
    return {n: float(np.rad2deg(np.sqrt(np.mean(ang[:, i] ** 2)))) for i, n in enumerate(names)}


def score_against_truth(result, truth: dict, skel, mask: Optional[np.ndarray] = None) -> dict:
    """Joint angles (E1), relative positions (E2) and segment orientations of a BodyResult vs a truth dict.

    Args:
        result: object with names, n_quat (T, S, 4), n_pos (T, S, 3) (e.g. `BodyResult`).
        truth: {"names", "n_quat", "n_pos"} (a simulated BodySession's truth).
        skel: the skeleton of `result` (joint definitions).
        mask: samples to score.
    Returns:
        {"joints": {joint: {...}}, "joint_rmse_max_deg", "joint_geodesic_max_deg", "position": {...}, "segment_orientation_deg": {...}}.
    Raises:
        SessionError: the truth lacks a segment of the result, or lengths differ.
    """
    names = list(result.names)
    tn = list(truth["names"])
    missing = [n for n in names if n not in tn]
    if missing:
        raise SessionError(_SRC, "truth.names", f"missing {missing}", "every segment of the estimate")
    idx = [tn.index(n) for n in names]
    q_ref, p_ref = np.asarray(truth["n_quat"])[:, idx], np.asarray(truth["n_pos"])[:, idx]
    if q_ref.shape[0] != np.shape(result.n_quat)[0]:
        raise SessionError(_SRC, "truth.n_quat", f"{q_ref.shape[0]} samples", f"{np.shape(result.n_quat)[0]}")
    joints = joint_angle_rmse(skel, result.n_quat, q_ref, mask)
    pos = relative_position_error(names, result.n_pos, p_ref, names[0], mask)
    seg = segment_orientation_error(names, result.n_quat, q_ref, np.deg2rad(pos["heading_deg"]), mask)
    return {"joints": joints, "joint_rmse_max_deg": max((v["all"] for v in joints.values()), default=float("nan")),
            "joint_geodesic_max_deg": max((v["geodesic"] for v in joints.values()), default=float("nan")),
            "position": pos, "segment_orientation_deg": seg}


# ---------------------------------------------------------------- Vicon comparison (gaittoolbox)

def _proj_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation to M (chordal mean of a summed set of rotations), via SVD."""
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _yaw_of_x(R: np.ndarray) -> np.ndarray:
    """Heading (rad) of the x axis of (…, 3, 3) rotations."""
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def fit_segment_alignment(R_est: dict, R_ref: dict, root: str = "Pelvis") -> tuple[np.ndarray, dict]:
    """W, {segment: C_s} with R_est,s(t) ≈ W R_ref,s(t) C_s (module docstring, "segment").

    Given W, each C_s is the chordal mean

        C_s(W) = proj_SO3( Σ_t R_ref,s(t)ᵀ Wᵀ R_est,s(t) ).

    W = Rz(ψ_W) (both systems are z up) is NOT fitted jointly with the C_s: for upright segments a heading
    of W and a common heading of all C_s trade off almost exactly (Rz(a)·R·Rz(−a) ≈ R), and such a common
    heading would mix flexion into abduction. Instead the root fixes it: both systems define the pelvis x axis
    anterior, so ψ_W makes the estimate's pelvis x axis free of a lateral component in the reference pelvis
    frame, C_root(ψ_W)[1, 0] = 0 (started from the circular mean heading difference of the root x axes).

    Args:
        R_est, R_ref: {segment: (T, 3, 3)} rotations on the same samples; both must hold `root`.
    Returns:
        (W (3, 3), {segment: C_s (3, 3)}).
    """
    from scipy.optimize import minimize_scalar

    if root not in R_est or root not in R_ref:
        raise SessionError(_SRC, "root", f"{root} missing", "the root segment in both rotation sets")
    segs = [s for s in R_est if s in R_ref]
    # K_s[j,i,k,l] = Σ_t R_ref[t,j,i] R_est[t,k,l], so that Σ_t R_refᵀ Wᵀ R_est = Σ_jk W[k,j] K_s[j,i,k,l]
    K = {s: np.einsum("tji,tkl->jikl", R_ref[s], R_est[s], optimize=True) for s in segs}

    def c_of(W, s):
        return _proj_so3(np.einsum("kj,jikl->il", W, K[s]))

    d = _yaw_of_x(R_est[root]) - _yaw_of_x(R_ref[root])
    psi0 = float(np.arctan2(np.mean(np.sin(d)), np.mean(np.cos(d))))
    res = minimize_scalar(lambda p: c_of(rz(p), root)[1, 0] ** 2, bounds=(psi0 - 0.5, psi0 + 0.5),
                          method="bounded", options={"xatol": 1e-10})
    W = rz(float(res.x))
    return W, {s: c_of(W, s) for s in segs}


def _stack(skel, q: dict, idx: np.ndarray) -> np.ndarray:
    return np.stack([q[n][idx] for n in skel.names], 1)


def compare_with_vicon(vicon: dict, est_quat: dict, method: str = "segment", align_s: Optional[float] = None,
                       max_shift: int = 5, joints=LOWER_JOINTS) -> dict:
    """Hip, knee and ankle angles of an estimate against the Vicon segments (module docstring).

    Args:
        vicon: `imugraph.io.gaittoolbox.read_gaittoolbox_vicon` output ("imu_index", "quat", "fs").
        est_quat: {MVN segment: (N_imu, 4) segment → n} at every IMU sample (index 0 = IMU sample 0).
        method: "segment" (per-segment alignment) or "offset" (mean per joint/axis).
        align_s: "segment" only: fit the alignment on the first align_s seconds and score the rest (None: fit
            on and score the whole window).
        max_shift: time shifts of the estimate searched, ± samples.
        joints: joints to score.
    Returns:
        {"method", "shift_samples", "n", "joints": {joint: {flexion, abduction, rotation, all, geodesic}},
         "mean_all_deg",
         "offsets_deg" (offset) or "alignment_deg" {segment: angle of C_s from the nominal axes} (segment)}.
    Raises:
        SessionError: unknown method, a missing segment, or an estimate too short for the Vicon window.
    """
    from imugraph.body.skeleton import lower_body

    if method not in ("segment", "offset"):
        raise SessionError(_SRC, "method", repr(method), "'segment' or 'offset'")
    skel = lower_body()
    need = sorted({s for j in joints for s in JOINTS[j]})
    for s in need:
        if s not in vicon["quat"] or s not in est_quat:
            raise SessionError(_SRC, "segments", f"{s} missing in {'vicon' if s not in vicon['quat'] else 'estimate'}",
                               f"quaternions for {need}")
    idx = np.asarray(vicon["imu_index"], int)
    n_imu = min(np.shape(est_quat[s])[0] for s in need)
    if idx[0] - max_shift < 0 or idx[-1] + max_shift >= n_imu:
        raise SessionError(_SRC, "est_quat", f"{n_imu} samples", f"samples {idx[0] - max_shift}..{idx[-1] + max_shift}")
    q_vic = {s: rotmat_to_quat(quat_to_rotmat(np.asarray(vicon["quat"][s], float)) @ VICON_AXES.get(s, np.eye(3)))
             for s in skel.names}
    n_align = idx.size if align_s is None or method != "segment" else int(round(align_s * float(vicon["fs"])))
    if not 10 <= n_align <= idx.size:
        raise SessionError(_SRC, "align_s", f"{align_s} s", f"at most the {idx.size / float(vicon['fs']):.2f} s window")
    scored = np.arange(idx.size) >= (n_align if n_align < idx.size else 0)
    best = None
    for shift in range(-max_shift, max_shift + 1):
        q_e = _stack(skel, est_quat, idx + shift)
        q_v = _stack(skel, q_vic, np.arange(idx.size))
        extra = {}
        if method == "segment":
            Re, Rv = quat_to_rotmat(q_e), quat_to_rotmat(q_v)
            _, C = fit_segment_alignment({s: Re[:n_align, i] for i, s in enumerate(skel.names) if s in need},
                                         {s: Rv[:n_align, i] for i, s in enumerate(skel.names) if s in need})
            q_v = np.stack([rotmat_to_quat(Rv[:, i] @ C.get(s, np.eye(3))) for i, s in enumerate(skel.names)], 1)
            extra["alignment_deg"] = {s: float(np.rad2deg(np.linalg.norm(logmap(c)))) for s, c in C.items()}
        err = {j: e[scored] for j, e in joint_angle_errors(skel, q_e, q_v, joints).items()}
        geo = joint_geodesic_errors(skel, q_e[scored], q_v[scored], joints, offsets=method == "offset")
        if method == "offset":
            extra["offsets_deg"] = {j: e.mean(0).tolist() for j, e in err.items()}
            err = {j: e - e.mean(0) for j, e in err.items()}
        table = _rmse_table(err, geo)
        mean_all = float(np.mean([v["all"] for v in table.values()]))
        if best is None or mean_all < best["mean_all_deg"]:
            best = dict({"method": method, "shift_samples": shift, "n": int(scored.sum()), "joints": table,
                         "mean_all_deg": mean_all, "align_s": align_s if method == "segment" else None}, **extra)
    return best


def vicon_joint_angles(vicon: dict) -> dict:
    """{joint: (N, 3) deg} of the Vicon segments with the nominal axis fix (no offset removed)."""
    from imugraph.body.skeleton import lower_body

    skel = lower_body()
    q = np.stack([rotmat_to_quat(quat_to_rotmat(np.asarray(vicon["quat"][s], float)) @ VICON_AXES.get(s, np.eye(3)))
                  for s in skel.names], 1)
    return joint_angles(skel, q)


__all__ = ["LOWER_JOINTS", "VICON_AXES", "best_heading", "compare_with_vicon", "fit_segment_alignment",
           "joint_angle_errors", "joint_angle_rmse", "joint_geodesic_errors", "relative_position_error", "rz", "score_against_truth",
           "segment_orientation_error", "vicon_joint_angles", "wrap_deg"]
