"""Helper B23 (issue 4): is the fixed lag's start causal? Rows after its bootstrap overwritten with garbage.

The fixed lag (imugraph.graphs.body_incremental, `mocap --lag S`) must not use samples it has not received yet. This
script runs it twice on one session: as recorded, and with every sensor's gyro and accelerometer rows from `cut` on
replaced by random finite values (gyro N(0, 3 rad/s), accelerometer N(0, 20 m/s²), magnetometer N(0, 1); seed 0),
where cut = the last row the auto bootstrap sees + `--margin` keyframe chunks. What may differ: nothing whose inputs
end before cut. The filtered (causal) output at sample i depends on the rows up to the end of the update that holds
i's keyframe, at most update_every × keyframe_every samples after i, so the samples [0, cut − update_every ×
keyframe_every) are compared; the lag-smoothed output ("lag_records") only for keyframes that left the window before
that (t ≤ t_cut − chunk − lag). Printed: the largest segment-orientation difference there (deg) and the largest
sensor-to-segment rotation difference of those keyframes' records (deg); 0 = causal. Simulations: also the clean
run's accuracy against the truth (worst joint RMSE (E1), position RMS), lag-smoothed and filtered, whole output.

    .venv/bin/python benchmarks/b23_lag_causal.py --sessions gtb,turned,qmt [--lag 1] [--set FIELD=VALUE ...]
                                                  [--variant NAME=FIELD=VALUE;FIELD=VALUE ...] [--out b23_causal.json]

Sessions: gtb (gaittoolbox S02 walk, 7 MTw, real; `init="auto"` switches its six leg sensors), turned (the 17-IMU
Xsens walk simulation of tests/test_body_init_motion.py, all 28 s (not 12: its bootstrap needs 16.5 s), every sensor turned 0–360° about the vertical: auto
switches most), qmt (the real 16-IMU qmt full body, first `--qmt-duration` s; no rest at its start: the N-pose is
"assumed", see b23_npose.py). Variants are BodyOptions fields on top of the defaults; "default" is always run.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import ast  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.output import write_json  # noqa: E402
from imugraph.config import data_dir  # noqa: E402

BVH = "gaittoolbox/xsens/S02-Trial-Walk-1.bvh"


def turned_session(seed: int = 3, duration_s: float = 12.0):
    """tests/test_body_init_motion.py's fixture: 17 IMUs, Xsens walk, each sensor turned about its vertical."""
    from imugraph.body.placement import Placement
    from imugraph.graphs.body_init import rz
    from imugraph.sim.body import motion_from_bvh, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    skel, mo = motion_from_bvh(data_dir() / BVH, rate_hz=60.0, npose_s=2.0, blend_s=1.0, duration_s=duration_s)
    rng = np.random.default_rng(seed)
    place = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
    place = {n: Placement(bRs=rz(rng.uniform(0.0, 2 * np.pi)) @ p.bRs, b_pos=p.b_pos) for n, p in place.items()}
    prm = {n: SensorParams(gyro_bias=rng.normal(0.0, 0.01, 3), gyro_noise=np.full(3, 0.003),
                           acc_noise=np.full(3, 0.02), acc_bias=rng.normal(0.0, 0.05, 3)) for n in place}
    return simulate_body(mo, skel, place, prm, rng, name="turned")


def load(name: str, qmt_duration: float):
    if name == "gtb":
        from imugraph.io.gaittoolbox import read_gaittoolbox
        return read_gaittoolbox(data_dir() / "gaittoolbox" / "rawimu")
    if name == "turned":
        return turned_session(duration_s=28.0)
    if name == "qmt":
        from imugraph.io.qmt_body import read_qmt_body
        bs = read_qmt_body(data_dir() / "qmt_full_body" / "full_body_example_data.mat")
        return bs.slice(0, int(np.searchsorted(bs.t, bs.t[0] + qmt_duration)))
    raise SystemExit(f"unknown session {name!r}")


def garbage_after(bs, cut: int | None, seed: int = 0):
    """bs with every sensor's rows [cut:] replaced by random finite values (module docstring); cut None: the same
    rows, copied (the clean run uses such copies too: numpy's results may differ in the last bits with the memory
    layout of the readers' arrays, 2e-11 on the gaittoolbox walk's bootstrap, nothing to do with causality)."""
    rng = np.random.default_rng(seed)
    out = {}
    for n, s in bs.sensors.items():
        cut_s = len(s.t) if cut is None else cut
        m = len(s.t) - cut_s
        gyr, acc, mag = s.gyr.copy(), s.acc.copy(), s.mag.copy()
        gyr[cut_s:], acc[cut_s:] = rng.normal(0.0, 3.0, (m, 3)), rng.normal(0.0, 20.0, (m, 3))
        mag[cut_s:] = np.where(np.isfinite(mag[cut_s:]), rng.normal(0.0, 1.0, (m, 3)), np.nan)
        out[n] = dataclasses.replace(s, gyr=gyr, acc=acc, mag=mag)
    return dataclasses.replace(bs, sensors=out)


def _angle(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Rotation angle of qa⁻¹ qb, deg, as 2 atan2(|vec|, |w|) (no arccos: exact to 1e-14° near 0)."""
    from imugraph.geometry import quat_conj, quat_mul

    d = quat_mul(quat_conj(qa.reshape(-1, 4)), qb.reshape(-1, 4))
    return np.degrees(2 * np.arctan2(np.linalg.norm(d[:, 1:], axis=1), np.abs(d[:, 0]))).reshape(qa.shape[:-1])


def run(bs, opts, lag: float, margin: int) -> dict:
    from imugraph.graphs.body_incremental import solve_body_incremental

    bs = garbage_after(bs, None)                                  # contiguous copies, as the garbage run's
    c0 = time.process_time()
    res = solve_body_incremental(bs, opts, lag_s=lag)
    cpu = time.process_time() - c0
    boot = res.info["bootstrap"]
    t = np.asarray(bs.t, float)
    chunk = 5 * opts.keyframe_every                               # update_every (default 5) × keyframe_every samples
    last_boot_row = int(np.searchsorted(t, t[0] + boot["bootstrap_s"])) + opts.keyframe_every
    cut = min(t.size - 10, last_boot_row + margin * chunk)
    g = garbage_after(bs, cut)
    c1 = time.process_time()
    res_g = solve_body_incremental(g, opts, lag_s=lag)
    cpu += time.process_time() - c1
    n_cmp = cut - chunk
    filt = _angle(res.info["filtered"].n_quat[:n_cmp], res_g.info["filtered"].n_quat[:n_cmp])
    recs, recs_g = res.info["lag_records"], res_g.info["lag_records"]
    n_k = min(len(recs), len(recs_g))
    lag_rows = int(np.searchsorted(t, t[cut] - lag - (t[chunk] - t[0])))
    lagged = _angle(res.n_quat[:lag_rows], res_g.n_quat[:lag_rows]) if lag_rows > 0 else np.zeros(1)
    place_d = []
    for k in range(n_k):
        if k * opts.keyframe_every >= lag_rows:                       # regular keyframes: an upper bound on kf[k]
            break
        for n, (bRs, _) in recs[k]["place"].items():
            bRs_g = recs_g[k]["place"][n][0]
            place_d.append(np.degrees(np.linalg.norm(_logmap(bRs.T @ bRs_g))))
    im = res.info.get("init_motion") or {}          # lag_init_causal only (the default stream does not report it)
    truth = {}
    if bs.truth is not None and "n_quat" in bs.truth:      # simulations: the clean run's accuracy, whole output
        from imugraph.body.evaluate import score_against_truth
        for key, r in (("lag", res), ("filtered", res.info["filtered"])):
            sc = score_against_truth(r, bs.truth, bs.skeleton)
            truth[key] = {"joint_rmse_max_deg": sc["joint_rmse_max_deg"], "pos_rms_cm": 100 * sc["position"]["rms_m"]}
    return {"cpu_s": cpu, "bootstrap_s": boot["bootstrap_s"], "cut_row": cut, "cut_t": float(t[cut] - t[0]),
            "compared_rows": n_cmp, "filtered_max_deg": float(filt.max()),
            "filtered_identical": bool(np.array_equal(res.info["filtered"].n_quat[:n_cmp],
                                                      res_g.info["filtered"].n_quat[:n_cmp])), "lag_rows": lag_rows,
            "lag_max_deg": float(lagged.max()), "place_max_deg": float(max(place_d) if place_d else 0.0),
            "switched": im.get("_switched"), "truth": truth, "npose": res.info.get("npose")}


def _logmap(R):
    from imugraph.geometry import logmap
    return logmap(R)


def _parse_set(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, v = it.split("=", 1)
        try:
            out[k.strip()] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            out[k.strip()] = v
    return out


def main(argv=None) -> int:
    from imugraph.graphs.body_model import BodyOptions

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sessions", default="gtb,turned")
    p.add_argument("--lag", type=float, default=1.0)
    p.add_argument("--margin", type=int, default=2, help="keyframe chunks after the bootstrap before the garbage")
    p.add_argument("--qmt-duration", type=float, default=40.0)
    p.add_argument("--variant", action="append", default=[], metavar="NAME=FIELD=VALUE;…",
                   help="a named set of BodyOptions fields, e.g. causal=lag_init_causal=True")
    p.add_argument("--out", default="b23_causal.json")
    a = p.parse_args(argv)
    variants = {"default": {}}
    for v in a.variant:
        name, rest = v.split("=", 1)
        variants[name] = _parse_set([x for x in rest.split(";") if x])
    rows, result = [], {"command": " ".join(sys.argv), "lag": a.lag, "runs": {}}
    for sname in a.sessions.split(","):
        bs = load(sname, a.qmt_duration)
        for vname, kw in variants.items():
            r = run(bs, BodyOptions(**kw), a.lag, a.margin)
            result["runs"][f"{sname}/{vname}"] = r
            rows.append((sname, vname, r))
            print(f"{sname:7s} {vname:12s} bootstrap {r['bootstrap_s']:6.2f} s, garbage from {r['cut_t']:6.2f} s: "
                  f"filtered max {r['filtered_max_deg']:.3g}° (bit-identical {r['filtered_identical']}), lag max {r['lag_max_deg']:.3g}°, "
                  f"bRs max {r['place_max_deg']:.3g}°"
                  + "".join(f"; vs truth {k} worst joint {v['joint_rmse_max_deg']:.2f}°, pos RMS {v['pos_rms_cm']:.2f} cm"
                            for k, v in r["truth"].items()) + f"  (switched {sorted(r['switched'] or [])}; CPU {r['cpu_s']:.1f} s)",
                  flush=True)
    print("wrote", write_json(a.out, result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
