"""x-IMU3 body sessions (imugraph.io.xio_body): the real 7-sensor recording, and what the common grid costs.

Part "real" (../shared/data/xio_lower_body, no ground truth): the reader's clock and dropout figures, then the batch
body solver (imugraph.graphs.body.solve_body_batch, BodyOptions defaults, without and with magnetometers) with
its CPU time, and per joint the range (min, max) of flexion / abduction / rotation over the motion (t 1.5–15 s)
and the offset of the last 2 s of rest from the N-pose (the subject stands still at both ends: a plausibility
figure, not an error).

Part "sim" (ground truth): the Xsens MVN walk of gaittoolbox (cmu-style BVH, benchmarks/body_bench.py set-up,
lower body, one seed) resampled at 400 Hz, then sensed three ways and solved by the same batch solver:
    ideal       every sensor sampled at 50 Hz on one clock (what the solver would get from synchronous sensors)
    xio_grid    each sensor on its own clock as the x-IMU3s are (rate 50 Hz × (1 + ε), ε uniform ±0.2 %, phase
                uniform in one step, 2 % of the samples dropped, never more than 2 in a row), written as x-IMU3
                CSV folders and read by `read_ximu3_body` (timestamps, linear (X1) onto one grid)
    xio_index   the same files aligned by sample index from each sensor's first sample, dropouts ignored (what a
                reader that trusted the sample count would do)
Scored against the truth at the session's own times (imugraph.body.evaluate.score_against_truth, t ≥ 3 s):
joint-angle RMSE max over joints, and the mean over joints.

    .venv/bin/python benchmarks/xio_body.py [--part real|sim|both] [--seeds 0] [--duration 20]
        [--interp linear,cubic,akima] [--skew 0.002] [--drop 0.02] [--no-phase]

--interp: the `read_ximu3_body(interp=)` variants compared (sim: each scored; real: RMS difference of the joint
angles from the linear one's). --skew/--drop/--no-phase: the sim's clock error, dropped fraction (single or double
dropouts at least 4 samples apart, simulated then removed: a lost packet the sensor did sample) and phase.

Writes bench_out/xio_body.json.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.body_bench import motion_path, sensor_params  # noqa: E402
from imugraph.body.skeleton import LOWER_BODY  # noqa: E402
from imugraph.config import data_dir  # noqa: E402

FOLDERS = {"Pelvis": "pelvis 00000001 (UDP)", "LeftUpperLeg": "Left Upper Leg 00000002 (UDP)",
           "LeftLowerLeg": "Left Lower Leg 00000003 (UDP)", "LeftFoot": "Left Foot 00000004 (UDP)",
           "RightUpperLeg": "Right Upper Leg 00000005 (UDP)", "RightLowerLeg": "Right Lower Leg 00000006 (UDP)",
           "RightFoot": "Right Foot 00000007 (UDP)"}
G = 9.80665


def _solve(session, use_mag=False):
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions

    c0 = time.process_time()
    res = solve_body_batch(session, BodyOptions(use_mag=use_mag))
    return res, time.process_time() - c0


def part_real(interps: tuple = ("linear",)) -> dict:
    from imugraph.body.angles import joint_angles
    from imugraph.io.xio_body import read_ximu3_body

    c0 = time.process_time()
    bs = read_ximu3_body(data_dir() / "xio_lower_body")
    out = {"read_cpu_s": time.process_time() - c0, "samples": bs.n, "rate_hz": bs.rate,
           "clock": bs.meta["clock"], "dropouts_total": bs.meta["dropouts_total"],
           "rates_hz": {k: v["rate_hz"] for k, v in bs.meta["sensors"].items()}}
    clock = bs.meta["clock"]
    print(f"read: {bs.n} samples at {bs.rate:.3f} Hz, first stamps within {clock['first_stamp_spread_ms']:.1f}"
          f" ms, last within {clock['last_stamp_spread_ms']:.1f} ms; dropouts {bs.meta['dropouts_total']}")
    print("own rates (Hz):", {k: round(v, 3) for k, v in out["rates_hz"].items()})
    for use_mag in (False, True):
        res, cpu = _solve(bs, use_mag)
        ang = joint_angles(bs.skeleton, res.n_quat)
        move = (res.t > 1.5) & (res.t < 15.0)
        end = res.t > res.t[-1] - 2.0
        rows = {}
        for name, a in ang.items():
            a = np.asarray(a, float)
            rows[name] = {"min": np.nanmin(a[move], 0).round(1).tolist(),
                          "max": np.nanmax(a[move], 0).round(1).tolist(), "end_offset": np.nanmean(a[end], 0).round(1).tolist()}
        key = "mag" if use_mag else "no_mag"
        out[key] = {"solve_cpu_s": cpu, "npose": res.info.get("npose"), "joints": rows}
        print(f"\n{key}: solve CPU {cpu:.2f} s, N-pose {res.info.get('npose')}")
        print(f"{'joint':16s} {'flexion min/max':>16s} {'abduction':>14s} {'rotation':>14s}   "
              "end offset (flx, abd, rot)")
        for name, r in rows.items():
            mm = "  ".join(f"{lo:6.1f}/{hi:5.1f}" for lo, hi in zip(r["min"], r["max"]))
            print(f"{name:16s} {mm}   {r['end_offset']}")
        if not use_mag:
            base = {k: np.asarray(v, float) for k, v in ang.items()}
    for how in interps:                  # other resamplings: how far their joint angles are from the linear one's
        if how == "linear":
            continue
        other, cpu = _solve(read_ximu3_body(data_dir() / "xio_lower_body", interp=how))
        ang = joint_angles(bs.skeleton, other.n_quat)
        diff = {k: np.sqrt(np.nanmean((np.asarray(v, float) - base[k]) ** 2, 0)).round(2).tolist()
                for k, v in ang.items()}
        out[f"no_mag_{how}_vs_linear_rms_deg"] = diff
        print(f"\nno_mag, interp={how} (solve CPU {cpu:.2f} s): RMS difference of the joint angles from linear's "
              "(flx, abd, rot) °:", diff)
    return out


def _resample_motion(motion, tau):
    """BodyMotion at times tau: slerp of the segment quaternions, linear positions (from a 400 Hz motion)."""
    from imugraph.geometry import quat_slerp
    from imugraph.sim.body import BodyMotion

    t = motion.t
    j = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, t.size - 2)
    u = (tau - t[j]) / (t[j + 1] - t[j])
    q = quat_slerp(motion.n_quat[j], motion.n_quat[j + 1], np.repeat(u[:, None], motion.n_quat.shape[1], 1))
    p = motion.n_pos[j] + u[:, None, None] * (motion.n_pos[j + 1] - motion.n_pos[j])
    return BodyMotion(tau, motion.names, q, p)


def _write(folder: Path, stamps_us, s):
    folder.mkdir(parents=True)
    g, a = np.rad2deg(s.gyr), s.acc / G
    lines = [f"{k},{g[i, 0]:.6f},{g[i, 1]:.6f},{g[i, 2]:.6f},{a[i, 0]:.6f},{a[i, 1]:.6f},{a[i, 2]:.6f}"
             for i, k in enumerate(stamps_us)]
    (folder / "Inertial.csv").write_text("Timestamp (us),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),"
                                         "Accelerometer X (g),Accelerometer Y (g),Accelerometer Z (g)\n"
                                         + "\n".join(lines) + "\n")
    m = [f"{stamps_us[i] + 3000},{s.mag[i, 0]:.6f},{s.mag[i, 1]:.6f},{s.mag[i, 2]:.6f}"
         for i in range(0, len(stamps_us), 3)]
    (folder / "Magnetometer.csv").write_text("Timestamp (us),X (a.u.),Y (a.u.),Z (a.u.)\n" + "\n".join(m) + "\n")


def part_sim(seed: int, duration: float, skew: float = 0.002, drop: float = 0.02, phase: bool = True,
             interps: tuple = ("linear",)) -> dict:
    from dataclasses import replace

    from imugraph.body.evaluate import score_against_truth
    from imugraph.io.body_session import BodySession
    from imugraph.io.session import Session
    from imugraph.io.xio_body import read_ximu3_body
    from imugraph.sim.body import BodyMotion, motion_from_bvh, random_placements, simulate_body

    skel, motion = motion_from_bvh(motion_path("xsens"), rate_hz=400.0, npose_s=2.0, blend_s=1.0,
                                   duration_s=duration)
    idx = [skel.index(n) for n in LOWER_BODY]
    skel = skel.subset(LOWER_BODY)
    motion = BodyMotion(motion.t, skel.names, motion.n_quat[:, idx], motion.n_pos[:, idx])
    rng = np.random.default_rng(seed)
    placements = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
    params = sensor_params(list(placements), rng)
    T, t_end = 0.02, float(motion.t[-1]) - 0.1

    def truth_at(tau):
        m = _resample_motion(motion, tau)
        return {"names": list(skel.names), "n_quat": m.n_quat, "n_pos": m.n_pos}

    def score(res, session_t, t0):
        mask = session_t + t0 >= 3.0
        sc = score_against_truth(res, truth_at(session_t + t0), skel, mask)
        return {"joint_rmse_max_deg": sc["joint_rmse_max_deg"],
                "joint_rmse_mean_deg": float(np.mean([v["all"] for v in sc["joints"].values()]))}

    out = {}
    # ideal: one clock, 50 Hz
    tau = np.arange(0.0, t_end, T)
    ideal = simulate_body(_resample_motion(motion, tau), skel, placements, params, np.random.default_rng(seed + 100))
    ideal = replace(ideal, truth=None, meta={})
    res, cpu = _solve(ideal)
    out["ideal"] = dict(score(res, ideal.t, 0.0), solve_cpu_s=cpu, samples=ideal.n)
    # x-IMU3-like: own clock per sensor, dropouts, written as CSV and read back
    r2 = np.random.default_rng(seed + 200)
    raw = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seg in LOWER_BODY:
            eps, ph = r2.uniform(-skew, skew), (r2.uniform(0.0, T) if phase else 0.0)
            st = ph + np.arange(0.0, t_end - ph - 0.05, T * (1 + eps))
            keep = np.ones(st.size, bool)
            gone = r2.choice(np.arange(5, st.size - 5, 4), int(drop * st.size), replace=False)   # ≥ 4 apart
            keep[gone] = False
            keep[gone[: gone.size // 4] + 1] = False                    # a quarter of them 2 in a row
            s1 = simulate_body(_resample_motion(motion, st), skel, {seg: placements[seg]}, {seg: params[seg]},
                               np.random.default_rng(seed + 300 + LOWER_BODY.index(seg))).sensors[seg]
            # a UDP dropout loses a packet the sensor did sample: rows removed after the simulation
            s1 = replace(s1, t=s1.t[keep], gyr=s1.gyr[keep], acc=s1.acc[keep], mag=s1.mag[keep], quat=s1.quat[keep],
                     movement=None)
            st = st[keep]
            stamps = np.round((917.0 + st) * 1e6).astype(np.int64)
            _write(Path(tmp) / FOLDERS[seg], stamps, s1)
            raw[seg] = (st, s1)
        read = {how: read_ximu3_body(tmp, interp=how) for how in interps}
    for how, bs in read.items():
        t0 = bs.meta["clock"]["start_stamp_s"] - 917.0
        res, cpu = _solve(bs)
        key = "xio_grid" if how == "linear" else f"xio_grid_{how}"
        out[key] = dict(score(res, bs.t, t0), solve_cpu_s=cpu, samples=bs.n, dropouts=bs.meta["dropouts_total"])
    # by index: each sensor's samples from its first, the common count, times of the first sensor
    n = min(v[0].size for v in raw.values())
    first = raw[LOWER_BODY[0]][0][:n]
    t_idx = first - first[0]
    sensors = {seg: Session(t_idx, s.gyr[:n], s.acc[:n], s.mag[:n], None, None, "<index>", seg, {})
               for seg, (st, s) in raw.items()}
    naive = BodySession(t_idx, sensors, skel, None, "<index>", "index", {})
    res, cpu = _solve(naive)
    out["xio_index"] = dict(score(res, t_idx, first[0]), solve_cpu_s=cpu, samples=n)
    print(f"\nsim seed {seed}, {duration:g} s of the Xsens walk, lower body, batch, no magnetometers; clock skew "
          f"±{skew:g}, dropped {drop:g}, random phase {phase}:")
    for k, v in out.items():
        print(f"  {k:10s} joint RMSE max {v['joint_rmse_max_deg']:6.2f}°, mean {v['joint_rmse_mean_deg']:5.2f}°, "
              f"{v['samples']} samples, solve CPU {v['solve_cpu_s']:.2f} s")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=("real", "sim", "both"), default="both")
    p.add_argument("--seeds", default="0")
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--skew", type=float, default=0.002, help="sim: each sensor's rate error, uniform ±skew")
    p.add_argument("--drop", type=float, default=0.02, help="sim: fraction of the samples dropped")
    p.add_argument("--no-phase", action="store_true", help="sim: every sensor's first sample at t = 0")
    p.add_argument("--interp", default="linear", help="read_ximu3_body interp values, comma-separated")
    a = p.parse_args(argv)
    c0 = time.process_time()
    result = {"command": " ".join(sys.argv)}
    if a.part in ("real", "both"):
        result["real"] = part_real(tuple(a.interp.split(",")))
    if a.part in ("sim", "both"):
        result["sim"] = {s: part_sim(int(s), a.duration, a.skew, a.drop, not a.no_phase,
                                       tuple(a.interp.split(","))) for s in a.seeds.split(",")}
    result["cpu_s"] = time.process_time() - c0
    print(f"\ntotal CPU {result['cpu_s']:.1f} s")
    out = Path("bench_out")
    out.mkdir(exist_ok=True)
    (out / "xio_body.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
