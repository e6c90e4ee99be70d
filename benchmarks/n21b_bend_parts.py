"""Session 21 (helper N21b), issue 4a: which lever makes the graph's neck bend (body_neck N5) wrong on CMU 131_02?

Diagnosis only (the truth is used here, never in the estimator). The default batch solve (solve_body_batch's
steps: first pass(es), then the (N6) lever pass) is repeated keeping pb and x; then, with A = T8, D = Head,
l_A,D / l_A,up the T8 sensor's levers of the T8–Head (lumped) and Pelvis–T8 joints, bRs_A T8's N-pose placement:

    d̂ = bR̂s_A (l̂_A,D − l̂_A,up)           (the graph's T8 origin → head origin, T8 segment frame; N5)
    d  = bRs_A (l_A,D − l_A,up)            (truth: l_A,up = −bRs_Aᵀ b_pos_A, l_A,D = bRs_Aᵀ (d − b_pos_A),
                                            d = mean over the scored samples of R_T8ᵀ (p_Head − p_T8))
    d̂ − d = (bR̂s_A − bRs_A)(l̂_A,D − l̂_A,up)  +  bRs_A (l̂_A,D − l_A,D)  −  bRs_A (l̂_A,up − l_A,up)     (P1)
              "rot" (T8 placement)             "lD" (T8's head lever)       "lup" (T8's own origin)

each part in cm in T8's segment frame (x forward, y left, z up). The head side of the same lumped joint:
its head lever error in the head's segment frame, e_H = bRs_H (l̂_H,D − l_H,D), and that error carried into
T8's frame by the truth's neck motion, mean_t R_T8ᵀ R_Head e_H ("head→T8"): the T8-side lever of a soft joint
takes up, to first order, the mean of what the head side misplaces. Also: the bend error |Rot(o_D → d̂ − o_u)
vs Rot(o_D → d − o_u)| in degrees (split into components about T8's x, y, z), the N-pose placement rotation
errors of T8 and the head (deg), and (mag question (c)) the error of the head's orientation relative to T8
(mean of Log((R_T8ᵀ R_H)_trueᵀ (R_T8ᵀ R_H)_est) over the scored samples, deg: z = twist/heading, y = nod).

    .venv/bin/python benchmarks/n21b_bend_parts.py [--motions cmu131_02] [--seeds 0,1,2,3,4] [--mag off,on]
        [--out n21b_bend_parts.json] [--set FIELD=VALUE …] [--lumped-sigma CHILD=SIGMA …] [--loose-before S]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_bench import simulated_session  # noqa: E402
from benchmarks.common import print_table  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def solve_keep(session, opts):
    """solve_body_batch's passes without hinges (the default): (pb, x, result)."""
    from imugraph.graphs import body_neck
    from imugraph.graphs.body import build_problem, optimize_with_mag_noise
    from imugraph.graphs.body_output import make_result

    pb = build_problem(session, opts)
    x, passes, graph = optimize_with_mag_noise(pb)
    if opts.lever_prior_frame in ("estimated", "lumped"):
        x, info2 = body_neck.lever_pass(pb, x, graph)
        if info2 is not None:
            passes.append(info2)
    return pb, x, make_result(pb, x, {"passes": passes})


def _angle_deg(R: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def parts(pb, x, truth, mask, A="T8", D="Head", link="Neck") -> dict:
    """(P1) and the head side for one solve (module docstring)."""
    from imugraph.factors import body as bf
    from imugraph.geometry import logmap, quat_to_rotmat
    from imugraph.graphs.body_neck import _rot_between
    from imugraph.graphs.body_output import estimate_placements

    place = estimate_placements(pb, x)[0]
    skel = pb.skel
    names = list(truth["names"])
    jD = next(j for j, jt in enumerate(pb.joints) if jt.parent == A and jt.child == D)
    jup = next(j for j, jt in enumerate(pb.joints) if jt.child == A)
    lev = {(seg, j): np.asarray(x.atPoint3(bf.lever_key(i)), float) for i, (seg, j, _) in enumerate(pb.levers)}
    bRs_hat, bRs_t = place[A][0], np.asarray(truth["placements"][A]["bRs"])
    bpos_t = np.asarray(truth["placements"][A]["b_pos"])
    R = quat_to_rotmat(np.asarray(truth["n_quat"])[mask])
    P = np.asarray(truth["n_pos"])[mask]
    iA, iD = names.index(A), names.index(D)
    RA, RD = R[:, iA], R[:, iD]
    d_t_all = np.einsum("kji,kj->ki", RA, P[:, iD] - P[:, iA])
    d_t = d_t_all.mean(axis=0)
    l_up_t = -bRs_t.T @ bpos_t
    l_D_t = bRs_t.T @ (d_t - bpos_t)
    l_D, l_up = lev[(A, jD)], lev[(A, jup)]
    d_hat = bRs_hat @ (l_D - l_up)
    p_rot = (bRs_hat - bRs_t) @ (l_D - l_up)                                                   # (P1)
    p_lD = bRs_t @ (l_D - l_D_t)
    p_lup = -bRs_t @ (l_up - l_up_t)
    # head side: the head's lever of the same joint (head origin in the head sensor's frame)
    bRs_H, bpos_H = np.asarray(truth["placements"][D]["bRs"]), np.asarray(truth["placements"][D]["b_pos"])
    l_H_t = -bRs_H.T @ bpos_H
    e_H = bRs_H @ (lev[(D, jD)] - l_H_t)
    e_H_in_A = np.mean(np.einsum("kji,kjl,l->ki", RA, RD, e_H), axis=0)
    o_u = np.asarray(skel.offsets[skel.index(link)], float)
    o_D = np.asarray(skel.offsets[skel.index(D)], float)
    R_hat, R_tb = _rot_between(o_D, d_hat - o_u), _rot_between(o_D, d_t - o_u)
    bend_err = logmap(R_tb.T @ R_hat)
    # the head side per keyframe (H1: do the N-pose keyframes, straight neck, pull the rigid lever?)
    dk_H = head_side_points(pb, x, place, A, D, jD, jup)
    kf = pb.kf
    Rk, Pk = quat_to_rotmat(np.asarray(truth["n_quat"])[kf]), np.asarray(truth["n_pos"])[kf]
    dk_t = np.einsum("kji,kj->ki", Rk[:, iA], Pk[:, iD] - Pk[:, iA])
    still = kf <= pb.npose_idx[-1]
    mov = mask[kf]
    side = {"head_npose_cm": 100 * dk_H[still].mean(0), "true_npose_cm": 100 * dk_t[still].mean(0),
            "head_motion_cm": 100 * dk_H[mov].mean(0), "true_motion_cm": 100 * dk_t[mov].mean(0),
            "head_all_cm": 100 * dk_H.mean(0), "true_all_cm": 100 * dk_t.mean(0)}
    R_m = _rot_between(o_D, dk_H[mov].mean(0) - o_u)
    # T8's sensor position on T8 from each of its joints, b_pos(j) = b_j − bR̂s_A l̂_A,j, error vs the truth (cm):
    # the "lup" part of (P1) is b_pos(up) − b_pos; other joints (shoulders: stiff, not lumped) may place it better
    bpos_err = {}
    for j, jt in enumerate(pb.joints):
        if A in (jt.parent, jt.child):
            b_j = np.asarray(jt.b_parent if jt.parent == A else jt.b_child, float)
            bpos_err[jt.name] = (100 * (b_j - bRs_hat @ lev[(A, j)] - bpos_t)).tolist()
    others = [np.asarray(v) for n, v in bpos_err.items() if n != pb.joints[jD].name and n != pb.joints[jup].name]
    if others:
        bpos_err["mean_others"] = np.mean(others, axis=0).tolist()
    # truth only: the best RIGID joint between T8 and the head, R_T8 c − R_H h = p_H − p_T8 (least squares over the
    # scored samples, c in T8's frame, h in the head's): where a rigid lumped joint fits the true motion (P2)
    Mx = np.concatenate([RA, -RD], axis=2).reshape(-1, 6)
    ch = np.linalg.lstsq(Mx, (P[:, iD] - P[:, iA]).reshape(-1), rcond=None)[0]
    rigid = {"c_minus_d_cm": (100 * (ch[:3] - d_t)).tolist(), "h_cm": (100 * ch[3:]).tolist(),
             "rms_cm": float(100 * np.sqrt(np.mean((Mx @ ch - (P[:, iD] - P[:, iA]).reshape(-1)) ** 2) * 3))}
    # the same fit on ACCELERATIONS (second differences; the IMUs see these, not positions) (P3)
    M3 = np.concatenate([RA, -RD], axis=2)
    y3 = P[:, iD] - P[:, iA]
    Mdd = (M3[2:] - 2 * M3[1:-1] + M3[:-2]).reshape(-1, 6)
    ydd = (y3[2:] - 2 * y3[1:-1] + y3[:-2]).reshape(-1)
    chd = np.linalg.lstsq(Mdd, ydd, rcond=None)[0]
    rigid.update({"acc_c_minus_d_cm": (100 * (chd[:3] - d_t)).tolist(), "acc_h_cm": (100 * chd[3:]).tolist()})
    return {"side": {k: v.tolist() for k, v in side.items()}, "bpos_err_cm": bpos_err, "truth_rigid_fit": rigid,
            "bend_err_head_motion_deg": float(np.rad2deg(np.linalg.norm(logmap(R_tb.T @ R_m)))),
            "bend_err_head_motion_xyz_deg": np.rad2deg(logmap(R_tb.T @ R_m)).tolist(),
            "d_hat_cm": (100 * d_hat).tolist(), "d_true_cm": (100 * d_t).tolist(),
            "d_true_std_cm": (100 * d_t_all.std(axis=0)).tolist(),
            "err_cm": (100 * (d_hat - d_t)).tolist(), "rot_cm": (100 * p_rot).tolist(),
            "lD_cm": (100 * p_lD).tolist(), "lup_cm": (100 * p_lup).tolist(),
            "head_lever_cm": (100 * e_H).tolist(), "head_lever_in_T8_cm": (100 * e_H_in_A).tolist(),
            "bend_err_deg": float(np.rad2deg(np.linalg.norm(bend_err))),
            "bend_err_xyz_deg": np.rad2deg(bend_err).tolist(),
            "place_err_deg": {A: _angle_deg(bRs_hat.T @ bRs_t), D: _angle_deg(place[D][0].T @ bRs_H)}}


def head_side_points(pb, x, place, A, D, jD, jup) -> np.ndarray:
    """(K, 3) the head-side point of the lumped joint per keyframe, d_k^H = bR̂s_A (R_As,kᵀ (p_Ds,k + R_Ds,k l̂_D,D
    − p_As,k) − l̂_A,up): where the head sensor puts D's origin, in A's segment frame (estimate only)."""
    from imugraph.factors import body as bf
    sA, sD = pb.names.index(A), pb.names.index(D)
    lev = {(seg, j): np.asarray(x.atPoint3(bf.lever_key(i)), float) for i, (seg, j, _) in enumerate(pb.levers)}
    out = []
    for k in range(pb.K):
        TA, TD = x.atPose3(bf.pose_key(sA, k)), x.atPose3(bf.pose_key(sD, k))
        RA = TA.rotation().matrix()
        pD = TD.translation() + TD.rotation().matrix() @ lev[(D, jD)]
        out.append(place[A][0] @ (RA.T @ (pD - TA.translation()) - lev[(A, jup)]))
    return np.asarray(out)


def head_rel_error(res, truth, mask, A="T8", D="Head") -> dict:
    """Mean and RMS per axis of Log((R_Aᵀ R_D)_trueᵀ (R_Aᵀ R_D)_est), deg, in D's frame (z twist, y nod)."""
    from imugraph.geometry import logmap, quat_to_rotmat
    names, rn = list(truth["names"]), list(res.names)
    Rt = quat_to_rotmat(np.asarray(truth["n_quat"])[mask])
    Re = quat_to_rotmat(res.n_quat[mask])
    rel_t = np.swapaxes(Rt[:, names.index(A)], 1, 2) @ Rt[:, names.index(D)]
    rel_e = np.swapaxes(Re[:, rn.index(A)], 1, 2) @ Re[:, rn.index(D)]
    e = np.rad2deg(logmap(np.swapaxes(rel_t, 1, 2) @ rel_e))
    return {"mean_deg": e.mean(axis=0).tolist(), "rms_deg": np.sqrt(np.mean(e ** 2, axis=0)).tolist()}


def run_case(motion: str, seed: int, use_mag: bool, kw: dict | None = None) -> dict:
    from imugraph.body.evaluate import relative_position_error
    from imugraph.graphs.body_model import BodyOptions

    skel, session, mask = simulated_session(motion, seed)
    t0 = time.process_time()
    pb, x, res = solve_keep(session, BodyOptions(use_mag=use_mag, **(kw or {})))
    cpu = time.process_time() - t0
    truth = session.truth
    names = list(truth["names"])
    p_ref = np.asarray(truth["n_pos"])[:, [names.index(n) for n in res.names]]
    per = relative_position_error(res.names, res.n_pos, p_ref, "Pelvis", mask)["per_segment"]
    out = {"motion": motion, "seed": seed, "use_mag": use_mag, "cpu_s": cpu,
           "pos_cm": {n: 100 * per[n] for n in ("T8", "Neck", "Head")},
           "head_rel_T8": head_rel_error(res, truth, mask), **parts(pb, x, truth, mask)}
    out["d_fk_err_cm"] = fk_side_error(res, pb, truth, mask)
    return out


def fk_side_error(res, pb, truth, mask, A="T8", D="Head") -> list:
    """(P4) the graph's joint point J_k read from the OUTPUT's T8 origin (FK through the ties below T8):
    d_k = R̂_Aᵀ (J_k − p̂_A) over the scored keyframes, its mean minus the truth's mean d, cm (T8 frame)."""
    from imugraph.geometry import quat_to_rotmat
    names, rn = list(truth["names"]), list(res.names)
    kf = pb.kf[mask[pb.kf]]
    jH = next(i for i, n in enumerate(res.info["joint_names"]) if n.endswith("-" + D))
    J = res.info["joint_centres"][mask[pb.kf], jH]
    Re = quat_to_rotmat(res.n_quat[kf, rn.index(A)])
    d_e = np.einsum("kji,kj->ki", Re, J - res.n_pos[kf, rn.index(A)])
    R = quat_to_rotmat(np.asarray(truth["n_quat"])[mask])
    P = np.asarray(truth["n_pos"])[mask]
    d_t = np.einsum("kji,kj->ki", R[:, names.index(A)], P[:, names.index(D)] - P[:, names.index(A)]).mean(0)
    return (100 * (d_e.mean(0) - d_t)).tolist()


def patch_lumped(per_child: dict, loose_before: float | None) -> None:
    """Diagnosis only: body._joint_model / factors_at patched so that the lumped joint with child c gets σ
    per_child[c], and all lumped joints ×100 σ at keyframes before `loose_before` s (which data place the point)."""
    import gtsam
    import imugraph.graphs.body as B
    orig_model, orig_at, now = B._joint_model, B.factors_at, {"t": 0.0}

    def factors_at(pb, k):
        now["t"] = float(pb.kf_t[k])
        return orig_at(pb, k)

    def joint_model(pb, jt):
        if not jt.lumped:
            return orig_model(pb, jt)
        sig = per_child.get(jt.child, pb.opts.lumped_joint_sigma_m)
        if loose_before is not None and now["t"] < loose_before:
            sig *= 100.0
        return gtsam.noiseModel.Isotropic.Sigma(3, sig)

    B.factors_at, B._joint_model = factors_at, joint_model


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motions", default="cmu131_02")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--mag", default="off,on", help="comma-separated of off, on")
    ap.add_argument("--out", default="n21b_bend_parts.json")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="BodyOptions field (Python literal), repeatable; default: the default model")
    ap.add_argument("--lumped-sigma", action="append", default=[], metavar="CHILD=SIGMA",
                    help="DIAGNOSIS ONLY (patches imugraph.graphs.body._joint_model here): σ of the lumped joint whose "
                         "child is CHILD, both passes, m (e.g. Head=0.005, T8=0.005)")
    ap.add_argument("--loose-before", type=float, default=None, metavar="S",
                    help="DIAGNOSIS ONLY: lumped joints ×100 σ at keyframes before S seconds (the N-pose + blend)")
    a = ap.parse_args(argv)
    if a.lumped_sigma or a.loose_before is not None:
        patch_lumped({k: float(v) for k, v in (x.split("=", 1) for x in a.lumped_sigma)}, a.loose_before)
    import ast
    kw = {k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.set)}
    recs = []
    f = lambda v: " ".join(f"{c:+.2f}" for c in v)  # noqa: E731
    for m in a.motions.split(","):
        for s in (int(v) for v in a.seeds.split(",")):
            for mag in a.mag.split(","):
                r = run_case(m, s, mag == "on", kw)
                recs.append(r)
                print(f"  {m} s{s} mag {mag}: head {r['pos_cm']['Head']:.2f} cm, bend err {r['bend_err_deg']:.2f}° "
                      f"({f(r['bend_err_xyz_deg'])}), d̂−d {f(r['err_cm'])} = rot {f(r['rot_cm'])} + lD "
                      f"{f(r['lD_cm'])} + lup {f(r['lup_cm'])}; head lever {f(r['head_lever_cm'])} → in T8 "
                      f"{f(r['head_lever_in_T8_cm'])}; place err {r['place_err_deg']}; head rel T8 mean "
                      f"{f(r['head_rel_T8']['mean_deg'])} rms {f(r['head_rel_T8']['rms_deg'])}", flush=True)
                print("     " + "; ".join(f"{k} {f(v)}" for k, v in r["side"].items())
                      + f"; bend err from head side, motion {r['bend_err_head_motion_deg']:.2f}°", flush=True)
                print("     truth's best rigid T8–head joint (P2): c − d " + f(r["truth_rigid_fit"]["c_minus_d_cm"])
                      + " cm, head-side h " + f(r["truth_rigid_fit"]["h_cm"]) + f" cm, residual RMS "
                      f"{r['truth_rigid_fit']['rms_cm']:.2f} cm; on accelerations (P3): c − d "
                      + f(r["truth_rigid_fit"]["acc_c_minus_d_cm"]) + ", h " + f(r["truth_rigid_fit"]["acc_h_cm"]),
                      flush=True)
                print("     (P4) J from the output's T8 origin: d error " + f(r["d_fk_err_cm"]) + " cm", flush=True)
                print("     T8 sensor position error from each joint (cm): "
                      + "; ".join(f"{k} {f(v)}" for k, v in r["bpos_err_cm"].items()), flush=True)
    print()
    print_table([[f"{r['motion']} s{r['seed']} {'mag' if r['use_mag'] else 'no-mag'}", r["pos_cm"]["Head"],
                  r["bend_err_deg"], f(r["err_cm"]), f(r["rot_cm"]), f(r["lD_cm"]), f(r["lup_cm"]),
                  f(r["head_lever_in_T8_cm"]), f(r["head_rel_T8"]["mean_deg"])] for r in recs],
                ["case", "head cm", "bend err °", "d̂−d cm", "rot", "lD", "lup", "head lever→T8", "head rel T8 mean °"])
    payload = {"command": "benchmarks/n21b_bend_parts.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "options": kw, "lumped_sigma": a.lumped_sigma, "loose_before": a.loose_before,
               "records": recs}
    print(f"\nwrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
