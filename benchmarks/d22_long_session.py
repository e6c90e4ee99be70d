"""Session 22 (helper D22): cost of the body diagnosis against the recording's length (docs/diagnose_body.md).

Host "xsens_loop": a 7-sensor lower-body session of any length built from the Xsens MVN walk BVH
(gaittoolbox/xsens/S02-Trial-Walk-1.bvh, 25 s): `imugraph.sim.body.motion_from_bvh` (2 s N-pose, 1 s blend,
10 Hz low-pass, 60 Hz) gives copy 0; every further copy is the BVH part of the same motion turned about the
vertical so that its pelvis heading continues the previous copy's last one and shifted so that its root
continues from there, joined by a 1 s blend (segment quaternions slerped with a smoothstep, root position by a
cubic Hermite with both ends' velocities); the whole motion is low-passed again at 10 Hz (zero phase) and
simulated with random placements and the MEMS errors of benchmarks.body_bench (`simulated_session`'s set-up),
cut at --duration s. Nothing copied from the data directory. Host "real_walk": the REAL gaittoolbox walk
(7 Xsens MTw, 100 Hz, 25 s). Host "xsens_loop100" (session 23): "xsens_loop" simulated at 100 Hz (the
same noise σ per sample). Host "qmt": the real 16-IMU recording through imugraph.io.qmt_body (if present).

    .venv/bin/python benchmarks/d22_long_session.py --host xsens_loop --durations 45,90,180 [--opt FIELD=VALUE]
    .venv/bin/python benchmarks/d22_long_session.py --host real_walk --durations 12.5,25 --lm-trace [--chunk 8]
    .venv/bin/python benchmarks/d22_long_session.py --host xsens_loop100 --durations 180 [--profile] (session 23)
    .venv/bin/python benchmarks/d22_long_session.py --host qmt --durations 100 --npose 40,44 (session 23)
        (real_walk, qmt: the recording's first --durations seconds)

Prints, per duration, the verdict, CPU time of the whole diagnosis (process time), the phases and the LM
iterations of the base fit, the two simulations and the stage-2 refits; writes bench_out/<out>.
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

from benchmarks.output import write_json  # noqa: E402

BLEND_LOOP_S = 1.0


def _yaw(q: np.ndarray) -> float:
    """Heading of a (w, x, y, z) quaternion: yaw of its rotated x axis."""
    from imugraph.geometry import quat_to_rotmat
    R = quat_to_rotmat(q)
    return float(np.arctan2(R[1, 0], R[0, 0]))


def looped_motion(duration_s: float, rate_hz: float | None = None):
    """(skeleton, BodyMotion) of the looped Xsens walk, at least duration_s long (module doc); rate_hz: the
    sample rate (None: body_bench's 60 Hz; session 23: 100 Hz, the real walk's rate)."""
    from scipy.signal import butter, filtfilt

    from benchmarks.body_bench import BLEND_S, NPOSE_S, RATE_HZ, motion_path
    from imugraph.body.skeleton import LOWER_BODY
    from imugraph.geometry import quat_continuous, quat_mul, quat_normalize, quat_slerp, rotvec_to_quat
    from imugraph.sim.body import BodyMotion, motion_from_bvh

    rate = RATE_HZ if rate_hz is None else float(rate_hz)
    skel, m = motion_from_bvh(motion_path("xsens"), rate_hz=rate, npose_s=NPOSE_S, blend_s=BLEND_S)
    dt = 1.0 / rate
    root = m.n_pos[:, 0]
    body = m.t >= NPOSE_S + BLEND_S - 1e-9
    qb, rb = m.n_quat[body], root[body]
    q_all, r_all = [m.n_quat], [root]
    nb = int(round(BLEND_LOOP_S / dt))
    u = np.arange(1, nb + 1) / (nb + 1)
    s = u * u * (3 - 2 * u)                                          # smoothstep
    while (sum(len(x) for x in q_all) - 1) * dt < duration_s + 1.0:
        q_end, r_end = q_all[-1][-1], r_all[-1][-1]
        v_end = (r_all[-1][-1] - r_all[-1][-2]) / dt
        psi = _yaw(q_end[0]) - _yaw(qb[0, 0])                        # pelvis heading continues
        qz = rotvec_to_quat(np.array([0.0, 0.0, psi]))
        c, sn = np.cos(psi), np.sin(psi)
        Rz = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        q_new = quat_mul(np.broadcast_to(qz, qb.shape), qb)
        r_rel = (rb - rb[0]) @ Rz.T
        v_new = (r_rel[1] - r_rel[0]) / dt
        T = (nb + 1) * dt
        p1 = r_end + 0.5 * (v_end + v_new) * T                       # where the next copy starts
        p1[2] = rb[0, 2]
        # (L1) blend: slerp per segment, root by cubic Hermite between (r_end, v_end) and (p1, v_new)
        qbl = np.stack([quat_slerp(q_end, q_new[0], np.full(q_end.shape[0], sk)) for sk in s])
        h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
        rbl = (h00[:, None] * r_end + h10[:, None] * T * v_end + h01[:, None] * p1 + h11[:, None] * T * v_new)
        q_all += [qbl, q_new]
        r_all += [rbl, p1 + r_rel]
    q = np.concatenate(q_all)
    r = np.concatenate(r_all)
    t = np.arange(q.shape[0]) * dt
    b, a = butter(4, 10.0 * 2 * dt)
    q = quat_normalize(filtfilt(b, a, quat_continuous(q), axis=0))
    r = filtfilt(b, a, r, axis=0)
    keep = t <= duration_s + 1e-9
    q, r, t = q[keep], r[keep], t[keep]
    idx = [skel.index(n) for n in LOWER_BODY]
    skel_l = skel.subset(LOWER_BODY)
    n_pos = skel.forward_kinematics(q, r)
    return skel_l, BodyMotion(t, skel_l.names, q[:, idx], n_pos[:, idx])


def looped_session(duration_s: float, seed: int, rate_hz: float | None = None):
    """The simulated 7-sensor session of the looped walk (module doc), at rate_hz (None: 60 Hz)."""
    from benchmarks.body_bench import sensor_params
    from imugraph.sim.body import random_placements, simulate_body

    skel, motion = looped_motion(duration_s, rate_hz)
    rng = np.random.default_rng(seed)
    placements = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
    return simulate_body(motion, skel, placements, sensor_params(list(placements), rng), rng,
                         name=f"xsens_loop_{duration_s:.0f}s_seed{seed}"
                         + ("" if rate_hz is None else f"_{rate_hz:g}Hz"))


def first_seconds(session, duration: float):
    """The session's first `duration` seconds (every per-sample array cut; the N-pose is at the start)."""
    from dataclasses import fields, replace

    t = np.asarray(session.t, float)
    n = int(np.searchsorted(t, t[0] + duration, side="right"))
    if n >= t.size:
        return session

    def cut(obj):
        ch = {f.name: getattr(obj, f.name)[:n] for f in fields(obj)
              if isinstance(getattr(obj, f.name), np.ndarray) and getattr(obj, f.name).shape[:1] == (t.size,)}
        return replace(obj, **ch)

    return replace(cut(session), sensors={k: cut(v) for k, v in session.sensors.items()})


def host_session(host: str, duration: float, seed: int):
    if host == "xsens_loop":
        return looped_session(duration, seed)
    if host == "xsens_loop100":                          # session 23: the same looped walk at 100 Hz
        return looped_session(duration, seed, 100.0)
    from imugraph.config import data_dir
    if host == "real_walk":
        from imugraph.io.body_session import read_body_session
        return first_seconds(read_body_session(data_dir() / "gaittoolbox" / "rawimu"), duration)
    if host == "qmt":
        from imugraph.io.qmt_body import read_qmt_body
        return first_seconds(read_qmt_body(data_dir() / "qmt_full_body" / "full_body_example_data.mat"), duration)
    raise ValueError(host)


def lm_trace(host: str, duration: float, seed: int, chunk_s=None, n_iter: int = 40) -> dict:
    """The base fit's LM one iteration at a time (BodyOptions defaults, the diagnosis's single pass): graph cost
    and CPU after each iteration, from the cold start (or the chunked start of body/chunked.py)."""
    import gtsam

    from imugraph.graphs.body import build_problem, full_graph, optimize
    from imugraph.graphs.body_model import BodyOptions
    from imugraph.graphs.body_neck import single_pass_options

    session = host_session(host, duration, seed)
    pb = build_problem(session, single_pass_options(BodyOptions()))
    g = full_graph(pb)
    c0 = time.process_time()
    start = pb.init
    if chunk_s is not None:
        from imugraph.diagnose.body.chunked import chunked_start
        start, its = chunked_start(pb, g, float(chunk_s), optimize)
        print(f"chunked start ({chunk_s} s): chunk iterations {its}, {time.process_time() - c0:.2f} s CPU")
    prm = gtsam.LevenbergMarquardtParams()
    prm.setMaxIterations(1)
    prm.setlambdaInitial(1e-2)
    prm.setlambdaLowerBound(1e-3)
    prm.setOrderingType(pb.opts.ordering.upper())
    opt = gtsam.LevenbergMarquardtOptimizer(g, start, prm)
    rows = [(0, float(g.error(start)), time.process_time() - c0)]
    for it in range(n_iter):
        opt.iterate()
        rows.append((it + 1, float(opt.error()), time.process_time() - c0))
    print(f"{host} {float(session.t[-1] - session.t[0]):.1f} s: LM cost per iteration (iteration, cost, CPU s):")
    for r in rows:
        print(f"  {r[0]:3d} {r[1]:.6g} {r[2]:.2f}")
    return {"host": host, "duration_s": float(session.t[-1] - session.t[0]), "chunk_s": chunk_s, "trace": rows,
            "relative_tol": pb.opts.relative_tol, "load": os.getloadavg()}


def run(host: str, duration: float, seed: int, options) -> dict:
    from imugraph.diagnose.body.run import diagnose_body

    session = host_session(host, duration, seed)
    dur = float(session.t[-1] - session.t[0])
    c0, t0 = time.process_time(), time.perf_counter()
    d = diagnose_body(session, options)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    its = {k: d.fits[k].info.get("iterations") for k in ("real", "A", "B")}
    its["chunks"] = d.fits["real"].info.get("chunk_iterations")
    refits = [{"name": e["name"], "sensor": e["sensor"], "iterations": e.get("refit_iterations")}
              for e in d.effects if e.get("stage") == 2]
    load = os.getloadavg()
    rec = {"host": host, "duration_s": dur, "n_sensors": len(session.sensors), "rate_hz": float(session.rate),
           "verdict": d.verdict, "sensor": d.sensor, "cpu_s": cpu, "wall_s": wall,
           "cpu_per_180s": cpu * 180.0 / dur, "timing": d.timing, "lm_iterations": its, "refits": refits,
           "load": load, "utc": time.strftime("%H:%M:%S", time.gmtime()),
           "top3": [{k: e[k] for k in ("name", "sensor", "loglik_gain", "shrink", "significant", "relevant")}
                    for e in d.effects[:3]]}
    print(f"{host} {dur:.0f} s, {len(session.sensors)} sensors: verdict {d.verdict} {d.sensor}; CPU {cpu:.1f} s "
          f"({rec['cpu_per_180s']:.1f} s per 180 s), wall {wall:.1f} s; phases "
          f"{ {k: round(v, 1) for k, v in d.timing.items()} }; LM iterations {its}; refits "
          f"{[(r['sensor'], r['iterations']) for r in refits]}; load {np.round(load, 1)} at {rec['utc']} UTC", flush=True)
    return rec


def main(argv=None) -> int:
    from benchmarks.diagnose_body import body_options

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--host", default="xsens_loop")
    p.add_argument("--durations", default="45,90,180")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="d22_long_session.json")
    p.add_argument("--opt", action="append", default=[], metavar="FIELD=VALUE",
                   help="a BodyDiagnoseOptions field (python literal value), repeatable")
    p.add_argument("--lm-trace", action="store_true", help="instead: the base fit's LM cost per iteration")
    p.add_argument("--chunk", type=float, default=None, help="with --lm-trace: start from the chunked start")
    p.add_argument("--npose", default=None, metavar="T0,T1", help="the N-pose window (BodyOptions.npose, as "
                   "`imugraph diagnose --npose`; e.g. 40,44 for --host qmt) and the diagnosis's N-pose check on "
                   "(session 23)")
    p.add_argument("--profile", action="store_true", help="cProfile the diagnoses: the top 40 functions by "
                   "cumulative CPU printed (session 23)")
    a = p.parse_args(argv)
    if a.lm_trace:
        recs = [lm_trace(a.host, float(d), a.seed, a.chunk) for d in a.durations.split(",") if d]
        print(f"wrote {write_json(a.out, {'args': vars(a), 'records': recs})}")
        return 0
    options = body_options(a.opt)
    if a.npose is not None:
        from dataclasses import replace

        from imugraph.commands.mocap import npose_window
        from imugraph.graphs.body_model import BodyOptions
        options = replace(options, body_options=BodyOptions(npose=npose_window(a.npose)), npose_check=True)
    if a.profile:
        import cProfile
        import pstats
        prof = cProfile.Profile(time.process_time)          # CPU time, not wall (shared machine)
        recs = prof.runcall(lambda: [run(a.host, float(d), a.seed, options) for d in a.durations.split(",") if d])
        pstats.Stats(prof).sort_stats("cumulative").print_stats(40)
    else:
        recs = [run(a.host, float(d), a.seed, options) for d in a.durations.split(",") if d]
    print(f"wrote {write_json(a.out, {'args': vars(a), 'records': recs})}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
