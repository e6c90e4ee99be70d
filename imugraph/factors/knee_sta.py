"""Thigh-sensor soft-tissue turn proportional to the knee flexion, seen through a hinge knee (option
`BodyOptions.knee_gain_segments`, issue 4b, session 21).

Why. On the real walk the thigh's rotation about its long axis is the left hip's error (shared with Xsens MVN),
and that error grows with the knee flexion (benchmarks/body_walk_diagnosis.py §7). A sensor strapped to the
thigh rides on muscle that moves with the knee: its turn about the femur's long axis â is modelled as

    bRs(k) = Exp(θ_k â) · bRs0,    θ_k = c_k + g · κ_k                                               (G1)

with κ_k the knee flexion at keyframe k (rad, from the hinge-free first pass, held fixed), g one unknown gain per
thigh (rad/rad) and c_k a slowly varying offset (strap settling, standing vs walking): a first-order Gauss–Markov
process of σ_c, correlation time τ_c (imugraph.factors.body_axial (S2)), or one constant c (τ_c None):

    c_0 ~ N(0, σ_c²),  c_k − ρ c_{k−1} ~ N(0, σ_c²(1 − ρ²)),  ρ = exp(−Δt/τ_c);    g ~ N(0, σ_g²)          (G2)

Only the knee hinge sees θ (the hip and knee centres lie on â: the joint factors (B2) are blind to it); the hinge
is body_axial's (S3) with θ_P = c_k + g κ_k and a rigid shank (θ_C = 0). Its Jacobians by the two new unknowns
follow from (S4): ∂e/∂c_k = ∂e/∂θ_P,  ∂e/∂g = κ_k ∂e/∂θ_P                                                (G3)

Two ways to estimate it (`BodyOptions.knee_gain_mode`):
- "graph": c_k and g are unknowns of the second (hinge) pass, jointly with the poses (the hinge also pulls them);
- "two-stage": the default graph is solved (no hinge pass); then, with the output's orientations held fixed, the
  knee-implied turn θ*_k (the turn about â that zeroes the hinge's internal-rotation component, (S3) row x̂) is
  split by linear least squares into the slow offset and the knee-locked part,
      min Σ_k (θ*_k − c_k − g κ_k)²/σ_IE² + (G2)                                                     (G4)
  (σ_IE the hinge's internal-rotation σ), so the hinge informs the sensor's turn and never the poses. With
  `knee_gain_screw_home` c_sh the knee itself turns internally by c_sh·κ (G5, screw-home) and θ* is first reduced
  by the turn that knee explains. θ* as the hinge (S3) sees it includes the knee's ab/adduction crossed with its
  flexion (the shank's y leaves the thigh's y–z plane when an abducted knee flexes); `knee_gain_turn` "cardan"
  removes that part too, θ* − θ*(Ry(α)Rx(β)Rz(γ_sh)) with α, β the knee's Cardan angles (≈ its internal rotation
  γ − γ_sh)                                                                                           (G6)
`knee_gain_apply`: "offset+gain" turns the output thigh by θ = c + g κ (G1); "gain" by g κ only (c read as the knee's
own slow internal rotation, not the sensor's).

Unlike body_axial's per-keyframe φ_k (Gauss–Markov, τ 0.1 s), (G1) has one free parameter per thigh for the part
locked to the knee, so noise in the hinge residual cannot be absorbed keyframe by keyframe.
Keys: C(s,k) the Vector1 c_k of sensor s, G(s) its Vector1 gain g.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.body.angles import FLEXION_SIGN
from imugraph.factors.body import _STRIDE, pose_key
from imugraph.factors.body_axial import axial_hinge_residual, gauss_markov_link, long_axis, scalar_prior
from imugraph.geometry import quat_mul, quat_to_rotmat, rotvec_to_quat

KNEE_FLEXION_SIGN = FLEXION_SIGN["Knee"]


def offset_key(s: int, k: int) -> int:
    """H(s,k): Vector1 offset c_k (rad) of sensor s (G1); one key per sensor (k = 0) with a constant offset."""
    return gtsam.symbol("h", s * _STRIDE + k)


def gain_key(s: int) -> int:
    """G(s): Vector1 gain g (rad/rad) of sensor s (G1)."""
    return gtsam.symbol("g", s)


def knee_flexion(pRd: np.ndarray) -> np.ndarray:
    """(…) knee flexion (rad) of thigh→shank rotations pRd (…, 3, 3): α of pRd = Ry(α)Rx(β)Rz(γ) (angles.py (A2))."""
    return KNEE_FLEXION_SIGN * np.arctan2(pRd[..., 0, 2], pRd[..., 2, 2])


def gain_hinge_factor(model: gtsam.noiseModel.Base, pose_P: int, pose_C: int, bRs0_P: np.ndarray, bRs0_C: np.ndarray,
                      a_P: np.ndarray, a_C: np.ndarray, c_key: int, g_key: int, kappa: float) -> gtsam.CustomFactor:
    """(S3) with θ_P = c + g κ (G1) and θ_C = 0, on the two sensor poses, c and g; Jacobians (S4), (G3)."""
    bRs0_P, bRs0_C = np.asarray(bRs0_P, float), np.asarray(bRs0_C, float)
    a_P, a_C, kappa = np.asarray(a_P, float), np.asarray(a_C, float), float(kappa)
    zero = np.zeros((2, 3))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
        ks = this.keys()
        RP = values.atPose3(ks[0]).rotation().matrix()
        RC = values.atPose3(ks[1]).rotation().matrix()
        th = float(values.atVector(ks[2])[0]) + kappa * float(values.atVector(ks[3])[0])     # (G1)
        if H is None:
            return axial_hinge_residual(RP, RC, bRs0_P, bRs0_C, a_P, a_C, th, 0.0)
        e, HP, HC, dP, _ = axial_hinge_residual(RP, RC, bRs0_P, bRs0_C, a_P, a_C, th, 0.0, jacobians=True)
        H[0] = np.hstack([HP, zero])               # Pose3 tangent (ω, v): rotation first
        H[1] = np.hstack([HC, zero])
        H[2] = dP.reshape(2, 1)                    # (G3)
        H[3] = (kappa * dP).reshape(2, 1)
        return e

    return gtsam.CustomFactor(model, [pose_P, pose_C, c_key, g_key], error)


# ---- graph glue (imugraph.graphs.body calls these; all no-ops unless opts.knee_gain_segments) ----------------

def knee_joint(pb, name: str):
    """The joint whose parent is thigh `name` and whose child is a hinge (opts.hinges; any child in the
    "two-stage" mode, which needs no hinge pass), or None."""
    two = pb.opts.knee_gain_mode == "two-stage"
    return next((jt for jt in pb.joints if jt.parent == name and (two or jt.child in pb.opts.hinges)), None)


def handles(pb, jt) -> bool:
    """True when joint `jt`'s hinge is this module's (G1)-(G3) one (it then replaces (B4))."""
    o = pb.opts
    return (o.knee_gain_mode == "graph" and pb.bRs_fixed is not None and jt.parent in o.knee_gain_segments
            and jt.child in o.hinges
            and jt.parent in pb.names and jt.child in pb.names and getattr(pb, "knee_kappa", None) is not None)


def _c_index(pb, k: int) -> int:
    return k if pb.opts.knee_gain_offset_tau_s is not None else 0


def prepare(pb, x: gtsam.Values) -> None:
    """κ_k of every modelled knee at the first-pass solution `x` (pb.bRs_fixed set): pb.knee_kappa {thigh: (K,)}."""
    pb.knee_kappa = {}
    for name in pb.opts.knee_gain_segments:
        jt = knee_joint(pb, name)
        if jt is None or name not in pb.names or jt.child not in pb.names:
            continue
        P, C = pb.names.index(name), pb.names.index(jt.child)
        RP = np.stack([x.atPose3(pose_key(P, k)).rotation().matrix() for k in range(pb.K)]) @ pb.bRs_fixed[name].T
        RC = np.stack([x.atPose3(pose_key(C, k)).rotation().matrix() for k in range(pb.K)]) @ pb.bRs_fixed[jt.child].T
        pb.knee_kappa[name] = knee_flexion(np.swapaxes(RP, -1, -2) @ RC)


def _hinge_sigmas(o) -> tuple:
    """σ (IE, AbAd) of a modelled knee's hinge (S3): knee_gain_hinge_sigmas_rad, else axial_hinge_sigmas_rad."""
    return o.knee_gain_hinge_sigmas_rad if o.knee_gain_hinge_sigmas_rad is not None else o.axial_hinge_sigmas_rad


def factors_at(pb, k: int) -> gtsam.NonlinearFactorGraph:
    """Keyframe k: the priors (G2) and the hinge (S3)+(G1) of each modelled knee."""
    g = gtsam.NonlinearFactorGraph()
    o = pb.opts
    model = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(_hinge_sigmas(o), float))
    for jt in pb.joints:
        if not handles(pb, jt):
            continue
        s, C = pb.names.index(jt.parent), pb.names.index(jt.child)
        if k == 0:
            g.add(scalar_prior(gain_key(s), o.knee_gain_sigma))
            g.add(scalar_prior(offset_key(s, 0), o.knee_gain_offset_sigma_rad))
        elif o.knee_gain_offset_tau_s is not None:
            g.add(gauss_markov_link(offset_key(s, k - 1), offset_key(s, k), pb.kf_t[k] - pb.kf_t[k - 1],
                                    o.knee_gain_offset_sigma_rad, o.knee_gain_offset_tau_s))
        g.add(gain_hinge_factor(model, pose_key(s, k), pose_key(C, k), pb.bRs_fixed[jt.parent], pb.bRs_fixed[jt.child],
                                long_axis(pb.skel, jt.parent), long_axis(pb.skel, jt.child),
                                offset_key(s, _c_index(pb, k)), gain_key(s), pb.knee_kappa[jt.parent][k]))
    return g


def insert_initial(pb, values: gtsam.Values) -> gtsam.Values:
    """`values` with c = 0 and g = 0 inserted for every modelled thigh (in place; returned)."""
    for jt in pb.joints:
        if not handles(pb, jt):
            continue
        s = pb.names.index(jt.parent)
        keys = [gain_key(s)] + [offset_key(s, k) for k in range(pb.K if pb.opts.knee_gain_offset_tau_s else 1)]
        for key in keys:
            if not values.exists(key):
                values.insert(key, np.zeros(1))
    return values


def knee_turn(pRd: np.ndarray, a_P: np.ndarray) -> np.ndarray:
    """(…) θ* (rad): the turn of the thigh about its long axis â (≈ ±z) that puts the shank's y axis (pRd[:, :, 1]
    in the thigh frame) into the thigh's y–z plane, i.e. zeroes the x̂ row of (S3): Exp(θ â) v ⟂ x̂."""
    v = pRd[..., :, 1]
    return -float(np.sign(a_P[2])) * np.arctan2(-v[..., 0], v[..., 1])


def screw_home_knee(pRd: np.ndarray, c_sh: float, left: bool) -> np.ndarray:
    """(…, 3, 3) the knee of the same flexion α and ab/adduction β as pRd = Ry(α)Rx(β)Rz(γ) whose internal rotation
    follows the flexion, ISB rotation = c_sh·κ (screw-home: the tibia turns internally as the knee flexes, ≈ 5–10°
    over 0–90°); with imugraph.body.angles' signs (rotation column = −side·γ, side +1 left) γ = −side·c_sh·κ  (G5)."""
    from imugraph.body.angles import cardan_yxz
    from imugraph.geometry import expmap

    a = cardan_yxz(pRd)
    side = 1.0 if left else -1.0
    gam = -side * c_sh * KNEE_FLEXION_SIGN * a[..., 0]
    e = np.eye(3)
    R = [expmap(a[..., 0, None] * e[1]), expmap(a[..., 1, None] * e[0]), expmap(gam[..., None] * e[2])]
    return R[0] @ R[1] @ R[2]


def two_stage(pb, res) -> dict:
    """(G4) per modelled thigh on the rigid output `res`: {thigh: (gain, c at every sample, κ at every sample)}."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    o, out, names = pb.opts, {}, list(res.names)
    hs = _hinge_sigmas(o)
    n = res.n_quat.shape[0]
    for name in o.knee_gain_segments:
        jt = knee_joint(pb, name)
        if jt is None or name not in names or jt.child not in names:
            continue
        RP, RC = quat_to_rotmat(res.n_quat[:, names.index(name)]), quat_to_rotmat(res.n_quat[:, names.index(jt.child)])
        pRd = np.swapaxes(RP, -1, -2) @ RC
        a_P, left = long_axis(pb.skel, name), name.startswith("Left")
        kappa, th = knee_flexion(pRd), knee_turn(pRd, a_P)
        if o.knee_gain_turn == "cardan":                # (G6): minus what the knee's own flexion, ab/adduction (and
            th = th - knee_turn(screw_home_knee(pRd, o.knee_gain_screw_home, left), a_P)    # screw-home) explain
        elif o.knee_gain_screw_home:                    # (G5): minus the screw-home increment only
            th = th - (knee_turn(screw_home_knee(pRd, o.knee_gain_screw_home, left), a_P)
                       - knee_turn(screw_home_knee(pRd, 0.0, left), a_P))
        kf, t = np.asarray(pb.kf), np.asarray(pb.session.t, float)
        K = kf.size
        rows, cols, vals, rhs = [], [], [], []          # unknowns: c_0..c_{K−1}, g (index K); whitened rows
        for k in range(K):                              # (G4) data rows
            rows += [len(rhs)] * 2
            cols += [k, K]
            vals += [1.0 / hs[0], kappa[kf[k]] / hs[0]]
            rhs.append(th[kf[k]] / hs[0])
        tau, sc = o.knee_gain_offset_tau_s, o.knee_gain_offset_sigma_rad
        rows.append(len(rhs)); cols.append(0); vals.append(1.0 / sc); rhs.append(0.0)           # c_0 ~ N(0, σ_c²)
        for k in range(1, K):                           # (G2): c_k − ρ c_{k−1} (τ None: c_k − c_{k−1} = 0, stiff)
            rho = float(np.exp(-(t[kf[k]] - t[kf[k - 1]]) / tau)) if tau is not None else 1.0
            sd = sc * np.sqrt(max(1.0 - rho ** 2, 1e-12)) if tau is not None else 1e-6
            rows += [len(rhs)] * 2
            cols += [k - 1, k]
            vals += [-rho / sd, 1.0 / sd]
            rhs.append(0.0)
        rows.append(len(rhs)); cols.append(K); vals.append(1.0 / o.knee_gain_sigma); rhs.append(0.0)   # g ~ N(0, σ_g²)
        A = sp.csr_matrix((vals, (rows, cols)), shape=(len(rhs), K + 1))
        sol = spsolve((A.T @ A).tocsc(), A.T @ np.asarray(rhs))
        out[name] = (float(sol[K]), np.interp(np.arange(n), kf, sol[:K]), kappa)
    return out


def _turn_thigh(pb, res, name: str, gain: float, c: np.ndarray, kappa: np.ndarray) -> dict:
    """(G1) on `res` in place: thigh `name` turned by θ = c + g κ (or g κ, knee_gain_apply "gain"); its info."""
    theta = gain * kappa + (c if pb.opts.knee_gain_apply == "offset+gain" else 0.0)
    i = list(res.names).index(name)
    res.n_quat[:, i] = quat_mul(res.n_quat[:, i], rotvec_to_quat(-theta[:, None] * long_axis(pb.skel, name)))
    return {"gain": gain, "offset_mean_rad": float(np.mean(c)), "offset_std_rad": float(np.std(c)),
            "theta_rms_rad": float(np.sqrt(np.mean(theta ** 2)))}


def apply_two_stage(pb, res) -> None:
    """(G4) then (G1) on `res` in place (knee_gain_mode "two-stage"); res.info["knee_gain"]."""
    info = {name: dict(_turn_thigh(pb, res, name, gain, c, kappa), mode="two-stage")
            for name, (gain, c, kappa) in two_stage(pb, res).items()}
    if info:
        res.info["knee_gain"] = info


def apply_to_result(pb, x: gtsam.Values, res) -> None:
    """Mode "two-stage": apply_two_stage. Mode "graph": turn each modelled thigh of `res` (in place) by (G1),
    nRb = nRs bRsᵀ Exp(−θ(t) â), θ(t) = c(t) + g κ(t) (or g κ(t), knee_gain_apply "gain"), c linear between
    keyframes, κ(t) the knee flexion of the (rigid) output at every sample; res.info["knee_gain"]."""
    if pb.opts.knee_gain_mode == "two-stage":
        return apply_two_stage(pb, res)
    out = {}
    names = list(res.names)
    for jt in pb.joints:
        if not handles(pb, jt) or not x.exists(gain_key(pb.names.index(jt.parent))):
            continue
        s = pb.names.index(jt.parent)
        gain = float(x.atVector(gain_key(s))[0])
        if pb.opts.knee_gain_offset_tau_s is not None:
            c = np.interp(np.arange(res.n_quat.shape[0]), pb.kf, [x.atVector(offset_key(s, k))[0] for k in range(pb.K)])
        else:
            c = np.full(res.n_quat.shape[0], float(x.atVector(offset_key(s, 0))[0]))
        RP, RC = quat_to_rotmat(res.n_quat[:, names.index(jt.parent)]), quat_to_rotmat(res.n_quat[:, names.index(jt.child)])
        out[jt.parent] = _turn_thigh(pb, res, jt.parent, gain, c, knee_flexion(np.swapaxes(RP, -1, -2) @ RC))
    if out:
        res.info["knee_gain"] = out
