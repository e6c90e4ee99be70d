"""Session 21 (helper N), issue 4a: where does the head's position error on CMU 131_02 come from?

Diagnosis, not a result table of the estimator: for each simulated session (benchmarks/body_bench.py) the
default batch graph is solved once, then

- the output's neck split u in nR_Neck = slerp(nR_T8, nR_Head, u) (the tie (K2) uses u = 1/2) is varied on a
  grid and the head's relative position error (E2) of each is scored against the truth (an ORACLE profile:
  which u would be right);
- the truth's neck bend relative to T8 (mean and std of Log(nR_T8ᵀ nR_Neck) per axis) and its own split u_true = Σ a·b / Σ b·b with a = Log(nR_T8ᵀ nR_Neck), b = Log(nR_T8ᵀ nR_Head) (truth);
- the head origin the graph itself holds (the T8–Head lumped joint centre J_k, keyframes) is scored in T8's
  frame against the truth, next to the output's FK head origin at u = 1/2 and u = 0:
      e_k = |R_T8ᵀ (p_Head − p_T8)_est − R_T8ᵀ (p_Head − p_T8)_true|                                   (D1)
- the output with the graph's constant neck bend (body_neck (N5)) and, as an ORACLE reference, with the truth's
  mean bend (chordal mean of nR_T8ᵀ nR_Neck over the scored samples), and the angle between the two bends;
- the data-driven split `imugraph.graphs.body_neck.choose_split` (no truth) and its cost profile.

    .venv/bin/python benchmarks/n21_neck_split.py [--motions cmu131_02] [--seeds 0,1,2,3,4] [--mag off|on]
        [--out n21_neck_split.json]
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

U_GRID = np.round(np.linspace(0.0, 1.0, 11), 2)


def _solve_keep(session, use_mag: bool):
    """The default batch solve (imugraph.graphs.body.solve_body_batch without options), keeping pb and x."""
    from imugraph.graphs.body import build_problem, optimize_with_mag_noise
    from imugraph.graphs.body_model import BodyOptions
    from imugraph.graphs.body_output import make_result

    pb = build_problem(session, BodyOptions(use_mag=use_mag))
    x, passes, _ = optimize_with_mag_noise(pb)
    return pb, x, make_result(pb, x, {"passes": passes})


def resplit(skel, n_quat: np.ndarray, n_pos: np.ndarray, u: float) -> tuple[np.ndarray, np.ndarray]:
    """(n_quat, n_pos) with nR_Neck = slerp(nR_T8, nR_Head, u) and the origins by forward kinematics (K1)."""
    from imugraph.geometry import quat_slerp
    q = n_quat.copy()
    iT, iN, iH = (skel.index(n) for n in ("T8", "Neck", "Head"))
    q[:, iN] = quat_slerp(q[:, iT], q[:, iH], np.full(q.shape[0], u))
    return q, skel.forward_kinematics(q, n_pos[:, 0])


def truth_bend(truth: dict, mask: np.ndarray) -> dict:
    """Mean and std over the scored samples of Log(nR_T8ᵀ nR_Neck) in the truth, degrees per axis (x, y, z)."""
    from imugraph.geometry import logmap, quat_to_rotmat
    names = list(truth["names"])
    R = quat_to_rotmat(np.asarray(truth["n_quat"])[mask])
    a = np.rad2deg(logmap(np.swapaxes(R[:, names.index("T8")], -1, -2) @ R[:, names.index("Neck")]))
    return {"mean_deg": a.mean(axis=0).tolist(), "std_deg": a.std(axis=0).tolist()}


def truth_split(truth: dict, mask: np.ndarray) -> float:
    from imugraph.geometry import logmap, quat_to_rotmat
    names = list(truth["names"])
    R = quat_to_rotmat(np.asarray(truth["n_quat"])[mask])
    RT, RN, RH = (R[:, names.index(n)] for n in ("T8", "Neck", "Head"))
    a = logmap(np.swapaxes(RT, -1, -2) @ RN)
    b = logmap(np.swapaxes(RT, -1, -2) @ RH)
    return float(np.sum(a * b) / np.sum(b * b))


def t8_frame_error(skel, q: np.ndarray, p_head: np.ndarray, p_t8: np.ndarray, truth: dict, idx: np.ndarray) -> float:
    """RMS of (D1) over samples idx, cm (q: estimated segment orientations at idx)."""
    from imugraph.geometry import quat_to_rotmat
    names = list(truth["names"])
    iT = skel.index("T8")
    Re = quat_to_rotmat(q[:, iT])
    Rt = quat_to_rotmat(np.asarray(truth["n_quat"])[idx, names.index("T8")])
    pt = np.asarray(truth["n_pos"])[idx]
    e = np.einsum("kji,kj->ki", Re, p_head - p_t8) - np.einsum("kji,kj->ki", Rt, pt[:, names.index("Head")]
                                                                 - pt[:, names.index("T8")])
    return float(100 * np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


def run_case(motion: str, seed: int, use_mag: bool) -> dict:
    from imugraph.body.evaluate import relative_position_error
    from imugraph.graphs import body_neck

    skel, session, mask = simulated_session(motion, seed)
    t0 = time.process_time()
    pb, x, res = _solve_keep(session, use_mag)
    cpu = time.process_time() - t0
    truth = session.truth
    names = list(truth["names"])
    p_ref = np.asarray(truth["n_pos"])[:, [names.index(n) for n in res.names]]
    iH = list(res.names).index("Head")
    prof = {}
    for u in U_GRID:
        q, p = resplit(skel, res.n_quat, res.n_pos, float(u))
        prof[float(u)] = 100 * relative_position_error(res.names, p, p_ref, "Pelvis", mask)["per_segment"]["Head"]
    # (D1) at the scored keyframes: the graph's joint centre J vs FK at u = 1/2 and u = 0
    jn = res.info["joint_names"]
    jH = next(i for i, n in enumerate(jn) if n.endswith("-Head"))
    kf = pb.kf
    sel = mask[kf]
    idx = kf[sel]
    J = res.info["joint_centres"][sel, jH]
    iT = list(res.names).index("T8")
    d1 = {"graph_J": t8_frame_error(skel, res.n_quat[idx], J, res.n_pos[idx, iT], truth, idx)}
    for u in (0.5, 0.0):
        q, p = resplit(skel, res.n_quat, res.n_pos, u)
        d1[f"fk_u{u:g}"] = t8_frame_error(skel, q[idx], p[idx, iH], p[idx, iT], truth, idx)
    # the head origin the graph holds: J_k (keyframes, linear in between) in place of FK's head, scored (E2)
    p = res.n_pos.copy()
    for c in range(3):
        p[:, iH, c] = np.interp(res.t, res.t[kf], res.info["joint_centres"][:, jH, c])
    alt = {"graph_J": 100 * relative_position_error(res.names, p, p_ref, "Pelvis", mask)["per_segment"]["Head"]}
    # the graph's constant neck bend: nR_Neck = nR_T8 · Rot(o_Head → d − o_Neck), d = T8 origin → head origin
    # in T8's frame from the graph's levers (body_neck.graph_bend)
    R_c = body_neck.graph_bend(pb, x, ("Head",))["Neck"][1]
    q = res.n_quat.copy()
    from imugraph.geometry import quat_mul, rotmat_to_quat
    iN = list(res.names).index("Neck")
    q[:, iN] = quat_mul(q[:, iT], np.broadcast_to(rotmat_to_quat(R_c), q[:, iT].shape))
    p = skel.forward_kinematics(q, res.n_pos[:, 0])
    alt["graph_bend"] = 100 * relative_position_error(res.names, p, p_ref, "Pelvis", mask)["per_segment"]["Head"]
    d1["graph_bend"] = t8_frame_error(skel, q[idx], p[idx, iH], p[idx, iT], truth, idx)
    # ORACLE references: the truth's mean neck bend in T8's frame (chordal mean), constant
    from imugraph.geometry import quat_to_rotmat
    from imugraph.graphs.body_output import project_so3
    Rt = quat_to_rotmat(np.asarray(truth["n_quat"])[mask])
    R_mean = project_so3(np.sum(np.swapaxes(Rt[:, names.index("T8")], -1, -2) @ Rt[:, names.index("Neck")], axis=0))
    q[:, iN] = quat_mul(q[:, iT], np.broadcast_to(rotmat_to_quat(R_mean), q[:, iT].shape))
    p = skel.forward_kinematics(q, res.n_pos[:, 0])
    alt["oracle_mean_bend"] = 100 * relative_position_error(res.names, p, p_ref, "Pelvis", mask)["per_segment"]["Head"]
    alt["bend_error_deg"] = float(np.rad2deg(np.arccos(np.clip((np.trace(R_mean.T @ R_c) - 1) / 2, -1, 1))))
    t1 = time.process_time()
    choice = body_neck.choose_split(pb, x)
    cpu_choice = time.process_time() - t1
    return {"motion": motion, "seed": seed, "use_mag": use_mag, "u_true": truth_split(truth, mask),
            "truth_neck_bend": truth_bend(truth, mask),
            "oracle_profile_cm": prof, "oracle_u": min(prof, key=prof.get), "d1_cm": d1,
            "alt_head_cm": alt,
            "chosen_u": choice["u"], "choice": choice, "solve_cpu_s": cpu, "choice_cpu_s": cpu_choice}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motions", default="cmu131_02")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--mag", choices=("off", "on"), default="off")
    ap.add_argument("--out", default="n21_neck_split.json")
    a = ap.parse_args(argv)
    recs = []
    for m in a.motions.split(","):
        for s in (int(v) for v in a.seeds.split(",")):
            r = run_case(m, s, a.mag == "on")
            recs.append(r)
            p = r["oracle_profile_cm"]
            print(f"  {m} s{s} mag {a.mag}: u_true {r['u_true']:.2f}, oracle u {r['oracle_u']:.1f}, head at u=0.5 "
                  f"{p[0.5]:.2f} cm, u=0 {p[0.0]:.2f} cm; chosen u {r['chosen_u']:.2f} → "
                  f"{np.interp(r['chosen_u'], U_GRID, [p[float(u)] for u in U_GRID]):.2f} cm; (D1) {r['d1_cm']}; "
                  f"alt {r['alt_head_cm']}",
                  flush=True)
    print()
    print_table([[f"{r['motion']} s{r['seed']}", r["u_true"], r["oracle_u"], r["chosen_u"]]
                 + [r["oracle_profile_cm"][float(u)] for u in U_GRID] for r in recs],
                ["case", "u_true", "oracle u", "chosen u"] + [f"u={u:g}" for u in U_GRID])
    payload = {"command": "benchmarks/n21_neck_split.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "records": recs}
    print(f"\nwrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
