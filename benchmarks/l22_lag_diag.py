"""Helper L22 (issue 4a in the fixed lag): where does the fixed lag lose against the batch? (diagnosis; truth used here only)

For one simulated motion and seed (benchmarks/body_bench.py) the batch (`solve_body_batch`) and the fixed lag
(`solve_body_incremental`, lag --lag s, auto bootstrap unless --bootstrap) solve the same session. Printed:

1. per joint: RMSE (E1 "all") batch / lag smoothed / lag filtered, and the geodesic error (E1g) per time window of
   --window s for the worst lag joint (when in the motion the lag loses);
2. per sensor: the sensor-to-segment rotation each path outputs against the truth's, |Log(bRs_trueᵀ bR̂s)| (deg)
   (the lag holds its bootstrap's), and its lever-free segment orientation error (deg, RMS over the motion);
3. what-if: the lag's output recomputed with the BATCH's placements (bRs, b_pos) instead of the bootstrap's — if
   the lag's joint errors fall to the batch's, the bootstrap's placement is the cause, not the stream.

    .venv/bin/python benchmarks/l22_lag_diag.py [--motion cmu131_02] [--seed 1] [--mag] [--lag 1]
        [--bootstrap S] [--window 1] [--set FIELD=VALUE ...] [--out l22_lag_diag.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import ast  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_bench import simulated_session  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def _angle_deg(R: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _with_placements(pb, records, place_psi):
    """The lag's records with every keyframe's placement replaced (what-if 3)."""
    from imugraph.graphs.body_lag_output import filtered_result
    recs = [dict(r, place=place_psi[0], psi=place_psi[1]) for r in records]
    return filtered_result(pb, recs, {})


def main(argv=None) -> int:
    from imugraph.body.angles import joint_angles
    from imugraph.body.evaluate import joint_angle_errors, joint_geodesic_errors, score_against_truth
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_incremental import solve_body_incremental
    from imugraph.graphs.body_model import BodyOptions

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motion", default="cmu131_02")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--mag", action="store_true")
    ap.add_argument("--lag", type=float, default=1.0)
    ap.add_argument("--bootstrap", type=float, default=None)
    ap.add_argument("--window", type=float, default=1.0)
    ap.add_argument("--set", action="append", default=[], help="BodyOptions FIELD=VALUE (python literal), both paths")
    ap.add_argument("--out", default="l22_lag_diag.json")
    a = ap.parse_args(argv)
    kw = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in a.set)}
    skel, sess, mask = simulated_session(a.motion, a.seed)
    opts = BodyOptions(use_mag=a.mag, **kw)
    res_b = solve_body_batch(sess, opts)
    res_l = solve_body_incremental(sess, opts, lag_s=a.lag, **({} if a.bootstrap is None else {"bootstrap_s": a.bootstrap}))
    res_f = res_l.info["filtered"]
    sc = {n: score_against_truth(r, sess.truth, skel, mask) for n, r in
          (("batch", res_b), ("lag", res_l), ("filtered", res_f))}
    truth_place = sess.truth["placements"]
    out = {"command": "benchmarks/l22_lag_diag.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "bootstrap": {k: v for k, v in res_l.info["bootstrap"].items() if isinstance(v, (int, float, str, bool))}}
    print(f"{a.motion} s{a.seed} {'mag' if a.mag else 'no-mag'} lag {a.lag:g}: bootstrap "
          f"{res_l.info['bootstrap'].get('bootstrap_s', a.bootstrap)} s of {sess.t[-1]:.1f} s")

    # 1. joints
    joints = sorted(sc["batch"]["joints"])
    print("\njoint RMSE (°): batch / lag / filtered")
    rows = {}
    for j in joints:
        rows[j] = [sc[n]["joints"][j]["all"] for n in ("batch", "lag", "filtered")]
        print(f"  {j:15s} {rows[j][0]:6.2f} {rows[j][1]:6.2f} {rows[j][2]:6.2f}")
    out["joints"] = rows
    worst = max(joints, key=lambda j: rows[j][1])
    ge = {n: joint_geodesic_errors(skel, r.n_quat, np.asarray(sess.truth["n_quat"]), (worst,))[worst]
          for n, r in (("batch", res_b), ("lag", res_l), ("filtered", res_f))}
    edges = np.arange(float(sess.t[mask][0]), float(sess.t[-1]) + 1e-9, a.window)
    ce = {n: joint_angle_errors(skel, r.n_quat, np.asarray(sess.truth["n_quat"]), (worst,))[worst]
          for n, r in (("batch", res_b), ("lag", res_l), ("filtered", res_f))}
    beta = joint_angles(skel, np.asarray(sess.truth["n_quat"]))[worst][:, 1]
    print(f"\n{worst} per {a.window:g} s window: geodesic error RMS (E1g) batch / lag / filtered, (E1) 'all' "
          f"(RMS over the 3 Cardan columns) batch / lag / filtered, truth's max |abduction| (°)")
    out["windows"] = []
    for t0 in edges:
        m = mask & (sess.t >= t0) & (sess.t < t0 + a.window)
        if m.sum() == 0:
            continue
        v = [float(np.sqrt(np.mean(ge[n][m] ** 2))) for n in ("batch", "lag", "filtered")]
        v += [float(np.sqrt(np.mean(ce[n][m] ** 2))) for n in ("batch", "lag", "filtered")]
        v.append(float(np.max(np.abs(beta[m]))))
        out["windows"].append([float(t0)] + v)
        print(f"  {t0:5.1f} s  " + " ".join(f"{x:6.2f}" for x in v[:3]) + "   " + " ".join(f"{x:6.2f}" for x in v[3:6])
              + f"   {v[6]:5.1f}")

    # 2. placements and segment orientation errors
    print("\nper sensor: bRs error vs truth (°) batch / lag(bootstrap); segment orientation RMS (°) batch / lag")
    out["sensors"] = {}
    for n in res_b.placements:
        Rt = np.asarray(truth_place[n]["bRs"], float)
        eb = _angle_deg(Rt.T @ res_b.placements[n]["bRs"])
        el = _angle_deg(Rt.T @ res_l.placements[n]["bRs"])
        ob, ol = sc["batch"]["segment_orientation_deg"][n], sc["lag"]["segment_orientation_deg"][n]
        out["sensors"][n] = [eb, el, ob, ol]
        print(f"  {n:15s} {eb:6.2f} {el:6.2f}   {ob:6.2f} {ol:6.2f}")

    # 3. what-if: the lag's keyframe states with the batch's placements
    recs = res_l.info.get("lag_records")
    if recs is not None:
        from imugraph.graphs.body import build_problem
        from imugraph.graphs.body_neck import single_pass_options
        pb = build_problem(sess, single_pass_options(opts))
        place_b = ({n: (p["bRs"], p["b_pos"]) for n, p in res_b.placements.items()}, recs[0]["psi"])
        alt = _with_placements(pb, recs, place_b)
        s_alt = score_against_truth(alt, sess.truth, skel, mask)
        same = _with_placements(pb, recs, (recs[-1]["place"], recs[-1]["psi"]))
        s_same = score_against_truth(same, sess.truth, skel, mask)
        print("\nwhat-if: lag states, batch placements (joint RMSE °): lag-as-is(recomputed) / with batch bRs")
        out["what_if"] = {}
        for j in joints:
            out["what_if"][j] = [s_same["joints"][j]["all"], s_alt["joints"][j]["all"]]
            print(f"  {j:15s} {out['what_if'][j][0]:6.2f} {out['what_if'][j][1]:6.2f}")
    seg = {n: {k: v * 100 for k, v in sc[n]["position"]["per_segment"].items()} for n in sc}
    out["positions_cm"] = seg
    print("\nworst segment positions (cm): " + ", ".join(
        f"{n} {max(seg[n].values()):.2f} {max(seg[n], key=seg[n].get)}" for n in seg))
    print(f"wrote {write_json(a.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
