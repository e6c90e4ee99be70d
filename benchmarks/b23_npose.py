"""Helper B23 (issue 4): body sessions that start moving — what the N-pose detection does, before and after.

Cases (data directory only, nothing copied):
    xsens_crop  17 IMUs simulated on the Xsens MVN walk (60 Hz, 2 s N-pose, 1 s blend, 12 s of BVH; random placements
                ≤ 30°, MEMS noise and biases, seed --seed), the first --crop s (default 5: N-pose, blend and the BVH's first 2 s, where the subject still stands) cut off;
    cmu_norest  CMU 131_01 simulated the same way, its first --crop s cut off (it moves throughout);
    xsens_mid   the same motion mirrored in time before its N-pose: [motion reversed | blend reversed | N-pose | N-pose |
                blend | motion] (a physically consistent trajectory), so its only rest (4 s) is in the middle;
    gtb_crop    the real gaittoolbox S02 walk (7 MTw, 100 Hz; standing ≈ 11 s) with its first 12 s cut off;
    qmt         the real qmt full body (16 IMUs, 100 s, no rest at its start), detection only unless --solve-qmt.
Per case: "today" — BodyOptions() as `mocap` runs it (npose_samples: "assumed" = the first 20 samples when no rest
starts the data), batch (and with --lag the fixed lag); "anywhere" — imugraph.graphs.body_init.find_npose (what
`mocap --npose-search anywhere` does): the refusal's one line, or the window found, then solved from its first sample
on. Simulations are scored against their truth (worst joint RMSE (E1), position RMS) on the rows both outputs cover
(xsens_mid: from the found rest on); the real walk by the knee flexion range (plausibility, no Vicon here).

    .venv/bin/python benchmarks/b23_npose.py [--cases xsens_crop,cmu_norest,xsens_mid,gtb_crop,qmt] [--lag 1] [--solve-qmt]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.output import write_json  # noqa: E402
from imugraph.config import data_dir  # noqa: E402
from imugraph.errors import SessionError  # noqa: E402

BVH = "gaittoolbox/xsens/S02-Trial-Walk-1.bvh"


def xsens_motion(duration_s: float = 12.0):
    from imugraph.sim.body import motion_from_bvh
    return motion_from_bvh(data_dir() / BVH, rate_hz=60.0, npose_s=2.0, blend_s=1.0, duration_s=duration_s)


def mirrored(mo):
    """[motion reversed … N-pose | N-pose … motion]: the trajectory run backwards into its own N-pose, then forwards."""
    n = mo.t.size
    dt = float(np.median(np.diff(mo.t)))
    q = np.concatenate([mo.n_quat[::-1], mo.n_quat[1:]])
    p = np.concatenate([mo.n_pos[::-1], mo.n_pos[1:]])
    return dataclasses.replace(mo, t=np.arange(2 * n - 1) * dt, n_quat=q, n_pos=p)


def simulate(skel, mo, seed: int):
    from imugraph.sim.body import random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    rng = np.random.default_rng(seed)
    place = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
    prm = {n: SensorParams(gyro_bias=rng.normal(0.0, 0.01, 3), gyro_noise=np.full(3, 0.003),
                           acc_noise=np.full(3, 0.02), acc_bias=rng.normal(0.0, 0.05, 3)) for n in place}
    return simulate_body(mo, skel, place, prm, rng, name="b23")


def load(case: str, seed: int, crop_s: float):
    if case == "cmu_norest":                        # CMU 131_01 without its N-pose and blend: moving throughout
        from benchmarks.body_bench import motion_path
        from imugraph.sim.body import motion_from_bvh
        skel, mo = motion_from_bvh(motion_path("cmu131_01"), rate_hz=60.0, npose_s=2.0, blend_s=1.0)
        bs = simulate(skel, mo, seed)
        return bs.slice(int(np.searchsorted(bs.t, bs.t[0] + crop_s)), bs.n)
    if case in ("xsens_crop", "xsens_mid"):
        skel, mo = xsens_motion()
        if case == "xsens_mid":
            return simulate(skel, mirrored(mo), seed)
        bs = simulate(skel, mo, seed)
        return bs.slice(int(np.searchsorted(bs.t, bs.t[0] + crop_s)), bs.n)
    if case == "gtb_crop":
        from imugraph.io.gaittoolbox import read_gaittoolbox
        bs = read_gaittoolbox(data_dir() / "gaittoolbox" / "rawimu")
        return bs.slice(int(np.searchsorted(bs.t, bs.t[0] + 12.0)), bs.n)
    if case == "qmt":
        from imugraph.io.qmt_body import read_qmt_body
        return read_qmt_body(data_dir() / "qmt_full_body" / "full_body_example_data.mat")
    raise SystemExit(f"unknown case {case!r}")


def solve(bs, opts, lag):
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_incremental import solve_body_incremental

    c0 = time.process_time()
    res = solve_body_batch(bs, opts) if lag is None else solve_body_incremental(bs, opts, lag_s=lag)
    return res, time.process_time() - c0


def score(res, bs, rows: np.ndarray) -> dict:
    """Scores on `rows` of bs: against the truth (simulations), else the knee flexion range (plausibility)."""
    from imugraph.body.angles import joint_angles

    mask = np.zeros(bs.n, bool)
    mask[rows] = True
    if bs.truth is not None and "n_quat" in bs.truth:
        from imugraph.body.evaluate import score_against_truth
        s = score_against_truth(res, bs.truth, bs.skeleton, mask)
        worst = max(s["joints"], key=lambda j: s["joints"][j]["all"])
        return {"joint_rmse_max_deg": s["joint_rmse_max_deg"], "worst": worst,
                "pos_rms_cm": 100 * s["position"]["rms_m"]}
    ang = joint_angles(bs.skeleton, res.n_quat)
    out = {}
    for k in ("RightKnee", "LeftKnee"):              # flexion min, max (deg), fraction outside [−15°, 160°]
        if k in ang:
            a = np.asarray(ang[k])[mask, 0]
            out[k] = [float(a.min()), float(a.max()), float(np.mean((a < -15) | (a > 160)))]
    return out


def run_case(case: str, seed: int, crop_s: float, lags: list, solve_it: bool) -> dict:
    from imugraph.graphs.body_init import find_npose
    from imugraph.graphs.body_model import BodyOptions, npose_samples

    bs = load(case, seed, crop_s)
    t = bs.t - bs.t[0]
    idx, method = npose_samples(bs, BodyOptions())
    rec = {"case": case, "samples": bs.n, "duration_s": float(t[-1]),
           "today": {"method": method, "window_s": [float(t[idx[0]]), float(t[idx[-1]])]}}
    print(f"{case}: {bs.n} samples, {t[-1]:.1f} s; today: N-pose {method} {t[idx[0]]:.2f}–{t[idx[-1]]:.2f} s", flush=True)
    try:
        _, m2, info = find_npose(bs, BodyOptions())
        rec["anywhere"] = dict(info, t0=info["t0"] - bs.t[0], t1=info["t1"] - bs.t[0])
        print(f"  anywhere: {m2} {info['t0'] - bs.t[0]:.2f}–{info['t1'] - bs.t[0]:.2f} s "
              f"(candidates {[[round(a - bs.t[0], 2), round(b - bs.t[0], 2)] for a, b in info.get('candidates', [])]})")
    except SessionError as exc:
        rec["anywhere"] = {"error": str(exc)}
        print(f"  anywhere: imugraph: error: {exc}")
    if not solve_it:
        return rec
    start = rec["anywhere"].get("start_row", 0) if "error" not in rec["anywhere"] else 0
    rows = np.arange(start, bs.n)
    for lag in lags:
        key = "batch" if lag is None else f"lag {lag:g}"
        res, cpu = solve(bs, BodyOptions(), lag)
        rec.setdefault("today", {})[key] = dict(score(res, bs, rows), cpu_s=cpu)
        print(f"  today {key}: {rec['today'][key]} (scored from {t[start]:.2f} s)", flush=True)
        if "error" in rec["anywhere"] or rec["anywhere"]["method"] != "found":
            continue
        cut = bs.slice(start, bs.n)
        res2, cpu2 = solve(cut, BodyOptions(npose=(rec["anywhere"]["t0"] + bs.t[0], rec["anywhere"]["t1"] + bs.t[0])), lag)
        rec["anywhere"][key] = dict(score(res2, cut, np.arange(cut.n)), cpu_s=cpu2)
        print(f"  anywhere {key}: {rec['anywhere'][key]}", flush=True)
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="xsens_crop,cmu_norest,xsens_mid,gtb_crop,qmt")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--crop", type=float, default=5.0, help="xsens_crop: seconds cut off the start")
    p.add_argument("--lag", type=float, default=None, help="also the fixed lag with this lag, s")
    p.add_argument("--solve-qmt", action="store_true", help="also solve the qmt file (≈ 30–250 s CPU)")
    p.add_argument("--out", default="b23_npose.json")
    a = p.parse_args(argv)
    lags = [None] + ([a.lag] if a.lag else [])
    out = {"command": " ".join(sys.argv), "cases": []}
    for case in a.cases.split(","):
        out["cases"].append(run_case(case, a.seed, a.crop, lags, case != "qmt" or a.solve_qmt))
    print("wrote", write_json(a.out, out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
