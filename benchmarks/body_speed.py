"""Issue 4d: speed of the body estimator, 17 IMUs × 60 s at 60 Hz (batch LM and fixed-lag smoothing).

Data: the Xsens MVN walk (../shared/data/gaittoolbox/xsens/S02-Trial-Walk-1.bvh, 25 s) through the
BVH-driven simulator (imugraph.sim.body: N-pose prefix, random placements up to 30°, MEMS-level noise and
bias), played forward, backward, forward, ... ("ping-pong", continuous poses) to --duration seconds.
Not timed: the simulation. Timed (wall clock, time.perf_counter; the machine may be shared): building the
problem (noise, N-pose, preintegration, initial values) and solving; fixed lag: the sum of the per-update
solver times after the batch bootstrap (--bootstrap-s: "auto" = until every sensor has moved enough,
imugraph.graphs.body_bootstrap; or seconds) (real-time factor = streamed
duration ÷ that sum; the bootstrap's own time is given apart) and the total including the per-sample output.
Peak memory: the process's peak resident set size (resource.getrusage ru_maxrss) after each stage, which
includes gtsam's C++ allocations (tracemalloc would see only Python's).
Accuracy (a sanity check here; issue 4a has its own runs): RMS error of every parent→child relative
rotation (deg), worst joint, and of segment origins relative to the pelvis (cm, world frame).

    .venv/bin/python benchmarks/body_speed.py [--duration 60] [--modes batch,lag,isam2] [--keyframe-every 6]
                                              [--lag 1.0] [--update-every 5] [--lag-keyframe-every 6]
                                              [--lag-iterations 1] [--bootstrap-s auto] [--factorization QR]
                                              [--unsensed SIGMA_DEG] [--unsensed-prior fixed] [--unsensed-chains Head]
                                              [--unsensed-npose-sigma DEG] [--unsensed-gain G]
                                              [--lag-set FIELD=VALUE ...]

--unsensed* set BodyOptions.unsensed_sigma_rad (given in degrees), unsensed_prior and unsensed_chains of the
batch (imugraph.graphs.body_chain: a second batch pass; the fixed-lag smoother does not use them).
--lag-set (helper L22) sets a BodyOptions field of the incremental modes, e.g. lag_bootstrap_marginal=True.

Writes bench_out/body_speed.json (--out-name to change).
"""

from __future__ import annotations

import argparse
import ast
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.output import write_json  # noqa: E402
from imugraph.config import data_dir  # noqa: E402
from imugraph.geometry import quat_conj, quat_mul, quat_to_rotmat, quat_to_rotvec  # noqa: E402
from imugraph.graphs.body import solve_body_batch  # noqa: E402
from imugraph.graphs.body_incremental import solve_body_incremental  # noqa: E402
from imugraph.graphs.body_model import BodyOptions  # noqa: E402
from imugraph.sim.body import BodyMotion, motion_from_bvh, nominal_placement, random_placements, simulate_body  # noqa: E402
from imugraph.sim.sensors import SensorParams  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def ping_pong(mot: BodyMotion, n: int) -> BodyMotion:
    """n samples of the motion played forward, backward, forward, ... (continuous poses)."""
    T = mot.t.size
    period = np.r_[np.arange(T), np.arange(T - 2, 0, -1)]
    idx = np.resize(period, n)
    dt = float(np.median(np.diff(mot.t)))
    return BodyMotion(t=np.arange(n) * dt, names=mot.names, n_quat=mot.n_quat[idx], n_pos=mot.n_pos[idx])


def make_session(duration: float, seed: int = 0):
    path = Path(data_dir()) / "gaittoolbox" / "xsens" / "S02-Trial-Walk-1.bvh"
    if not path.exists():
        raise SystemExit(f"{path}: not found (set IMUGRAPH_DATA)")
    skel, mot = motion_from_bvh(path, 60.0, skip_s=0.1, tie_unsensed=True)
    mot = ping_pong(mot, int(round(duration * 60.0)))
    rng = np.random.default_rng(seed)
    place = random_placements(skel, rng, 30.0)
    prm = {n: SensorParams(gyro_bias=rng.normal(0, 0.01, 3), gyro_noise=0.005, acc_noise=0.05,
                           acc_bias=rng.normal(0, 0.05, 3), mag_noise=0.01) for n in skel.sensed}
    sess = simulate_body(mot, skel, place, prm, rng)
    R0 = quat_to_rotmat(mot.n_quat[0, 0])
    psi0 = float(np.rad2deg(np.arctan2(R0[1, 0], R0[0, 0])))
    nom = {n: (nominal_placement(skel, n).bRs, nominal_placement(skel, n).b_pos) for n in skel.sensed}
    return sess, skel, nom, psi0


def accuracy(sess, skel, res) -> dict:
    tq, tp = sess.truth["n_quat"], sess.truth["n_pos"]
    joints = {}
    for i, p in enumerate(skel.parents):
        if p < 0:
            continue
        rt = quat_mul(quat_conj(tq[:, p]), tq[:, i])
        re = quat_mul(quat_conj(res.n_quat[:, p]), res.n_quat[:, i])
        e = np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(rt), re)), axis=1)
        joints[skel.names[i]] = float(np.rad2deg(np.sqrt(np.mean(e**2))))
    d = (tp - tp[:, :1]) - (res.n_pos - res.n_pos[:, :1])
    rel = np.sqrt(np.mean(np.sum(d**2, axis=2), axis=0)) * 100
    return {"joint_rms_deg": joints, "worst_joint_deg": max(joints.values()), "worst_relpos_cm": float(rel.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--modes", default="batch,lag")
    ap.add_argument("--keyframe-every", type=int, default=BodyOptions().keyframe_every)
    ap.add_argument("--lag", type=float, default=1.0)
    ap.add_argument("--update-every", type=int, default=5)
    ap.add_argument("--lag-keyframe-every", type=int, default=6)
    ap.add_argument("--bootstrap-s", default="auto",
                    help="batch bootstrap of the incremental modes: 'auto' (until enough motion), seconds, or 0: none")
    ap.add_argument("--factorization", default=None, help="QR or CHOLESKY (default: Cholesky after a bootstrap)")
    ap.add_argument("--lag-iterations", type=int, default=1)
    ap.add_argument("--unsensed", type=float, default=None, help="BodyOptions.unsensed_sigma_rad in degrees (batch)")
    ap.add_argument("--unsensed-prior", default="shared", help="BodyOptions.unsensed_prior")
    ap.add_argument("--unsensed-chains", default="", help="comma-separated distal segments (unsensed_chains)")
    ap.add_argument("--unsensed-npose-sigma", type=float, default=None, help="unsensed_npose_sigma_rad in degrees")
    ap.add_argument("--unsensed-gain", type=float, default=None, help="BodyOptions.unsensed_sigma_gain (rad per rad)")
    ap.add_argument("--lag-set", action="append", default=[], metavar="FIELD=VALUE",
                    help="BodyOptions field of the incremental modes (python literal; repeatable; helper L22)")
    ap.add_argument("--out-name", default="body_speed.json", help="file name under bench_out/")
    a = ap.parse_args(argv)
    sess, skel, nom, psi0 = make_session(a.duration)
    out = {"duration_s": a.duration, "rate_hz": 60.0, "sensors": len(sess.sensors), "samples": int(sess.t.size),
           "keyframe_every": a.keyframe_every, "peak_rss_after_sim_mb": peak_rss_mb(), "runs": {}}
    print(f"{len(sess.sensors)} IMUs × {a.duration:.0f} s × 60 Hz ({sess.t.size} samples); "
          f"peak RSS after simulation {out['peak_rss_after_sim_mb']:.0f} MB", flush=True)
    chain_kw = {} if a.unsensed is None else {
        "unsensed_sigma_rad": float(np.deg2rad(a.unsensed)), "unsensed_prior": a.unsensed_prior,
        "unsensed_chains": tuple(x for x in a.unsensed_chains.split(",") if x),
        "unsensed_npose_sigma_rad": None if a.unsensed_npose_sigma is None else float(np.deg2rad(a.unsensed_npose_sigma)),
        "unsensed_sigma_gain": a.unsensed_gain}
    out["unsensed"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in chain_kw.items()}
    opts = BodyOptions(placements=nom, npose_heading_deg=psi0, keyframe_every=a.keyframe_every, **chain_kw)
    for mode in a.modes.split(","):
        t0, c0 = time.perf_counter(), time.process_time()
        if mode == "batch":
            res = solve_body_batch(sess, opts)
            row = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                   "build_s": res.info["build_s"], "solve_s": res.info["solve_s"],
                   "iterations": [p["iterations"] for p in res.info["passes"]], "keyframes": res.info["keyframes"]}
        else:
            lag_set = {k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.lag_set)}
            lag_opts = BodyOptions(placements=nom, npose_heading_deg=psi0, keyframe_every=a.lag_keyframe_every, **lag_set)
            boot = a.bootstrap_s if a.bootstrap_s == "auto" else (float(a.bootstrap_s) or None)
            res = solve_body_incremental(sess, lag_opts, lag_s=None if mode == "isam2" else a.lag, smoother="batch",
                                         update_every=a.update_every, lag_iterations=a.lag_iterations,
                                         bootstrap_s=boot, factorization=a.factorization)
            u = res.info["update_s"]
            row = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                   "lag_s": None if mode == "isam2" else a.lag, "lag_set": a.lag_set,
                   "keyframe_every": a.lag_keyframe_every, "lag_iterations": a.lag_iterations,
                   "bootstrap": res.info["bootstrap"],
                   "update_every": a.update_every, "updates": int(u.size), "update_sum_s": float(u.sum()),
                   "update_p50_ms": float(np.median(u) * 1e3), "update_max_ms": float(u.max() * 1e3),
                   "realtime_factor": res.info["realtime_factor"],
                   "realtime_factor_total": a.duration / (time.perf_counter() - t0),
                   "failed_updates": res.info["failed_updates"],
                   "filtered": accuracy(sess, skel, res.info["filtered"])}
        row["peak_rss_mb"] = peak_rss_mb()
        row["accuracy"] = accuracy(sess, skel, res)
        out["runs"][mode] = row
        print(mode, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()
                     if k not in ("accuracy", "filtered")}, flush=True)
        print("   worst joint %.2f deg, worst relpos %.2f cm" % (row["accuracy"]["worst_joint_deg"],
                                                                 row["accuracy"]["worst_relpos_cm"]), flush=True)
    path = write_json(a.out_name, out)
    print("wrote", path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
