"""The real 16-IMU full-body recording (../shared/data/qmt_full_body, imugraph.io.qmt_body) through the body solver.

No ground truth. What is checked, and what it means:
    read      the reader's units and quaternion convention per sensor: |acc| and |gyr| at rest (the N-pose),
              the (Q1) fit residual of the file's quaternion, and the tilt error of nRs·acc at rest vs +z (Q2).
    lumbar    where the lower-back sensor sits between pelvis and upper back: the forward tilt (pitch, from the
              batch output's segment orientations) of the lower-back sensor's segment (L5, or L3 with
              --lower-back L3) regressed on T8's, both relative to the pelvis's, u = Σ Δθ_lb Δθ_T8 / Σ Δθ_T8²
              (Δθ = θ − θ_Pelvis); on the 17-sensor body the ties (K2) put L5 at u = ¼, L3 at ½.
    (a)       joint angles physically plausible: knee and elbow flexion percentiles (1, 50, 99) and min/max, and the
              fraction of samples outside [−15°, 160°] (hyperextension beyond 15° or flexion beyond 160°).
    (b)       agreement with the file's own quaternions (qmt's estimate, NOT truth; qmt's published example computes
              them per sensor with its 6D filter, each sensor's heading its own, so the per-segment heading
              figures are the comparable ones): per sensed segment s,
              nRs_file(t) ≈ Rz(ψ) · nRb_imugraph(t) · X_s with one common heading ψ and one constant X_s per segment
              (alternating least squares); the RMS angle of what is left, its heading-free part (the angle between
              the two estimates' vertical axes in the segment frame), and the same with a heading ψ_s per
              segment; then per joint with both segments sensed the RMS difference of the joint angles
              (flexion, abduction, rotation) computed from imugraph and from the file mapped by X_s.
    (c)       joint connections: the graph's joint centres J (info["joint_centres"], one per keyframe): the
              distance between a segment's two joint centres (e.g. hip → knee) is constant if the joint factors
              hold on a rigid segment; its std over keyframes (mm) and its mean vs the skeleton's length.
    (d)       batch vs fixed lag (`--lag` s, default 1): RMS segment-orientation difference per segment (deg, after
              the constant heading between the two outputs is removed) and RMS joint-angle differences.
    (e)       CPU time (time.process_time, one thread) per real-time second of each solve.
    lower     (--lower) the 7 lower-body sensors only (read_qmt_body(sensors=LOWER_BODY_SENSORS)): batch, CPU, and
              the RMS difference of its hip/knee/ankle angles from the 16-sensor batch's.

    .venv/bin/python benchmarks/qmt_full_body.py [--duration S] [--lag 1] [--no-lag] [--lower]
        [--init nominal|motion|auto] [--npose T0,T1] [--hinges RightLowerLeg,LeftLowerLeg] [--lower-back L5|L3]
    .venv/bin/python benchmarks/qmt_full_body.py --sim 0,1,2 [--sim-duration 30]    (the (H1)–(H3) check)

--duration: only the first S seconds (default: all 100 s). Writes bench_out/qmt_full_body.json.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import ast  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from imugraph.body.angles import JOINTS, joint_angles  # noqa: E402
from imugraph.config import data_dir  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402

FILE = "qmt_full_body/full_body_example_data.mat"
PLAUSIBLE = (-15.0, 160.0)            # flexion range accepted for knees and elbows, degrees
READ_REST = (1.0, 4.0)                # s after the start: standing still (every sensor's median |gyr| < 0.05 rad/s)


def _rz(psi: float) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _proj(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _angle_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))


def part_read(bs) -> dict:
    """Units and (Q1)/(Q2) per sensor over `READ_REST` (the subject stands still until ≈ 4.5 s; qmt's own filter
    needs ≈ 1 s to settle, so its first second is left out)."""
    t = bs.t - bs.t[0]
    idx, how = np.flatnonzero((t >= READ_REST[0]) & (t < READ_REST[1])), f"{READ_REST} s after the start"
    rows = {}
    for seg, s in bs.sensors.items():
        R = quat_to_rotmat(s.quat[idx])
        up = np.einsum("nij,nj->ni", R, s.acc[idx])
        tilt = np.degrees(np.arccos(np.clip(up[:, 2] / np.linalg.norm(up, axis=1), -1, 1)))
        fit = s.meta["quat_fit"]
        rows[seg] = {"acc_rest_norm": float(np.median(np.linalg.norm(s.acc[idx], axis=1))),
                     "gyr_rest_std": float(np.mean(np.std(s.gyr[idx], axis=0))),
                     "gyr_peak": float(np.max(np.linalg.norm(s.gyr, axis=1))),
                     "q1_residual_rad_s": fit["median_residual_rad_s"], "q1_angle_deg": fit["angle_deg"],
                     "q2_rest_tilt_deg_median": float(np.median(tilt))}
    print(f"rest ({how}): t {bs.t[idx[0]]:.2f}–{bs.t[idx[-1]]:.2f} s")
    print(f"{'segment':14s} |acc| rest  gyr std rest  |gyr| peak  (Q1) res rad/s  C angle  (Q2) rest tilt")
    for seg, r in rows.items():
        print(f"{seg:14s} {r['acc_rest_norm']:9.3f}  {r['gyr_rest_std']:12.4f}  {r['gyr_peak']:9.2f}  "
              f"{r['q1_residual_rad_s']:13.3f}  {r['q1_angle_deg']:6.0f}°  {r['q2_rest_tilt_deg_median']:8.2f}°")
    return {"npose": [float(bs.t[idx[0]]), float(bs.t[idx[-1]]), how], "sensors": rows}


def solve(bs, lag=None, init: str = "nominal", npose=None, hinges: tuple = (), extra: dict | None = None):
    """(BodyResult, CPU s, {child: δ}) of the batch solver or the fixed lag: BodyOptions defaults (no magnetometer
    here) but `npose` (None: detected), hinges, and BodyOptions.init "nominal" (the estimator's own start) or
    "motion" (imugraph.body.placement_motion (H1)–(H4), inside build_problem: its CPU time included; the batch's
    δ and ψ from info["init_motion"])."""
    from imugraph.graphs.body_model import BodyOptions

    c0 = time.process_time()
    opts = BodyOptions(npose=npose, hinges=tuple(h for h in hinges if h in bs.skeleton.sensed), init=init,
                       **(extra or {}))               # extra: more BodyOptions fields (--lag-set, helper B23)
    if lag is None:
        from imugraph.graphs.body import solve_body_batch
        res = solve_body_batch(bs, opts)
    else:
        from imugraph.graphs.body_incremental import solve_body_incremental
        res = solve_body_incremental(bs, opts, lag_s=lag)
    return res, time.process_time() - c0, res.info.get("init_motion") or {}


def _seg_R(res, name: str) -> np.ndarray:
    return quat_to_rotmat(res.n_quat[:, list(res.names).index(name)])


def part_lumbar(res, seg: str = "L5") -> dict:
    """u of the lower-back segment's forward tilt between pelvis (0) and T8 (1) (module docstring)."""
    def pitch(name):
        z = _seg_R(res, name)[:, :, 2]                     # the segment's long (up) axis in n
        x = _seg_R(res, "Pelvis")[:, :, 0]                  # forward: the pelvis's anterior axis, horizontal part
        fwd = x - x[:, 2:3] * np.array([0.0, 0.0, 1.0])
        fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
        return np.degrees(np.arctan2(np.sum(z * fwd, axis=1), z[:, 2]))
    p0 = pitch("Pelvis")
    d_l3, d_t8 = pitch(seg) - p0, pitch("T8") - p0
    d_l3, d_t8 = d_l3 - d_l3[:100].mean(), d_t8 - d_t8[:100].mean()
    u = float(np.sum(d_l3 * d_t8) / np.sum(d_t8 * d_t8))
    out = {"segment": seg, "u_between_pelvis_T8": u,
           "T8_minus_pelvis_pitch_range_deg": [float(d_t8.min()), float(d_t8.max())]}
    print(f"lumbar: {seg} forward tilt = {u:.2f} × T8's (relative to the pelvis; T8−pelvis pitch "
          f"{d_t8.min():.0f}…{d_t8.max():.0f}°); 17-sensor ties: L5 ¼, L3 ½")
    return out


def part_plausible(res, skel) -> dict:
    ang = joint_angles(skel, res.n_quat)
    out = {}
    for j in ("RightKnee", "LeftKnee", "RightElbow", "LeftElbow"):
        if j not in ang:
            continue
        f, ab = np.asarray(ang[j], float)[:, 0], np.asarray(ang[j], float)[:, 1]
        out[j] = {"p1_p50_p99": np.percentile(f, [1, 50, 99]).round(1).tolist(), "min": float(f.min()),
                  "max": float(f.max()), "outside_fraction": float(np.mean((f < PLAUSIBLE[0]) | (f > PLAUSIBLE[1]))),
                  "abduction_p1_p99": np.percentile(ab, [1, 99]).round(1).tolist()}
        print(f"(a) {j:11s} flexion p1/p50/p99 {out[j]['p1_p50_p99']}, min {f.min():.1f}, max {f.max():.1f}, "
              f"outside {PLAUSIBLE}: {100 * out[j]['outside_fraction']:.2f} %; abduction p1/p99 "
              f"{out[j]['abduction_p1_p99']}")
    return out


def part_qmt(res, bs) -> dict:
    """(b): agreement with the file's own estimate after X_s and a common heading (module docstring)."""
    names = [n for n in bs.skeleton.sensed if bs.sensors[n].quat is not None]
    Rf = {n: quat_to_rotmat(bs.sensors[n].quat) for n in names}
    Ri = {n: _seg_R(res, n) for n in names}
    psi, X = 0.0, {}
    for _ in range(20):                                  # alternate X_s | ψ and ψ | X_s
        X = {n: _proj(np.einsum("nji,njk->ik", _rz(psi) @ Ri[n], Rf[n])) for n in names}
        M = sum(np.einsum("nij,kj,nlk->il", Rf[n], X[n], Ri[n]) for n in names)    # Σ (Rf Xᵀ) Riᵀ
        psi = float(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1]))
    out = {"common_heading_deg": float(np.degrees(psi)), "segments": {}, "joints": {}}
    print(f"(b) vs the file's own quaternions (qmt's estimate, not truth): common heading {np.degrees(psi):.1f}°")
    print(f"    {'segment':14s} RMS common ψ  heading-free (tilt)  RMS own ψ_s")
    mapped = {}
    for n in names:
        E = np.einsum("nji,njk->nik", _rz(psi) @ Ri[n] @ X[n], Rf[n])
        Xo, po = X[n], psi                               # own heading ψ_s for this segment
        for _ in range(10):
            Xo = _proj(np.einsum("nji,njk->ik", _rz(po) @ Ri[n], Rf[n]))
            M = np.einsum("nij,kj,nlk->il", Rf[n], Xo, Ri[n])
            po = float(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1]))
        up_f = Rf[n][:, 2, :]                            # n's vertical in the sensor frame, each estimate
        up_i = (Ri[n] @ Xo)[:, 2, :]                     # imugraph's, mapped by X_s of the own-heading fit
        tilt = np.degrees(np.arccos(np.clip(np.sum(up_f * up_i, axis=1), -1, 1)))
        Eo = np.einsum("nji,njk->nik", _rz(po) @ Ri[n] @ Xo, Rf[n])
        r = {"rms_deg": float(np.sqrt(np.mean(_angle_deg(E) ** 2))), "tilt_rms_deg": float(np.sqrt(np.mean(tilt ** 2))),
             "own_heading_rms_deg": float(np.sqrt(np.mean(_angle_deg(Eo) ** 2))),
             "own_heading_offset_deg": float((np.degrees(po - psi) + 180.0) % 360.0 - 180.0)}
        out["segments"][n] = r
        print(f"    {n:14s} {r['rms_deg']:11.2f}°  {r['tilt_rms_deg']:18.2f}°  {r['own_heading_rms_deg']:10.2f}° "
              f"(ψ_s − ψ {r['own_heading_offset_deg']:+.1f}°)")
        mapped[n] = _rz(psi).T @ Rf[n] @ X[n].T           # the file's estimate in imugraph's segment frames
    from imugraph.geometry import rotmat_to_quat
    q_map = res.n_quat.copy()
    for n in names:
        q_map[:, list(res.names).index(n)] = rotmat_to_quat(mapped[n])
    a_i, a_f = joint_angles(bs.skeleton, res.n_quat), joint_angles(bs.skeleton, q_map)
    for j, (p, c) in JOINTS.items():
        if p in names and c in names and j in a_i:
            d = np.asarray(a_i[j], float) - np.asarray(a_f[j], float)
            d = (d + 180.0) % 360.0 - 180.0
            out["joints"][j] = np.sqrt(np.mean(d ** 2, axis=0)).round(2).tolist()
    print("    joint-angle RMS difference (flexion, abduction, rotation) °:", out["joints"])
    return out


def part_joints(res, skel) -> dict:
    """(c): std over keyframes of the distance between the two joint centres of each segment."""
    J = np.asarray(res.info["joint_centres"])
    jn = list(res.info["joint_names"])
    child = {n.split("-")[1]: i for i, n in enumerate(jn)}
    parent_of = {n.split("-")[1]: n.split("-")[0] for n in jn}
    out = {}
    for c, i in child.items():
        p = parent_of[c]
        if p not in child:                               # the root's joints: no proximal joint centre
            continue
        d = np.linalg.norm(J[:, i] - J[:, child[p]], axis=1)
        nom = float(np.linalg.norm(skel.neutral_positions()[skel.index(c)] - skel.neutral_positions()[skel.index(p)]))
        out[f"{p}: {parent_of[p]}-{p} → {p}-{c}"] = {"mean_m": float(d.mean()), "std_mm": float(1e3 * d.std()),
                                                      "skeleton_m": nom}
    print("(c) joint centres on one segment: distance mean (skeleton), std over keyframes")
    for k, v in out.items():
        print(f"    {k:44s} {v['mean_m']:.3f} m ({v['skeleton_m']:.3f})  std {v['std_mm']:.1f} mm")
    return out


def part_compare(a, b, skel, label: str, skel_b=None) -> dict:
    """(d): RMS orientation difference per segment after the constant heading between the outputs, joint angles."""
    skel_b = skel if skel_b is None else skel_b
    segs = [n for n in skel_b.sensed if n in skel.sensed and n in a.names and n in b.names]
    Ra = {n: _seg_R(a, n) for n in segs}
    Rb = {n: _seg_R(b, n) for n in segs}
    M = sum(np.einsum("nij,nkj->ik", Rb[n], Ra[n]) for n in segs)
    psi = float(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1]))
    seg = {n: float(np.sqrt(np.mean(_angle_deg(np.einsum("ji,njk->nik", _rz(psi), Rb[n]).transpose(0, 2, 1)
                                                @ Ra[n]) ** 2))) for n in segs}
    aa, ab = joint_angles(skel, a.n_quat), joint_angles(skel_b, b.n_quat)
    jts = {j: np.sqrt(np.mean(((np.asarray(aa[j], float) - np.asarray(ab[j], float) + 180) % 360 - 180) ** 2,
                              axis=0)).round(2).tolist() for j in aa if j in ab and all(s in segs for s in JOINTS[j])}
    print(f"{label}: heading between outputs {np.degrees(psi):.1f}°; segment RMS (deg):",
          {k: round(v, 2) for k, v in seg.items()})
    print(f"{label}: joint-angle RMS difference (flexion, abduction, rotation) °:", jts)
    return {"heading_deg": float(np.degrees(psi)), "segments_rms_deg": seg, "joints_rms_deg": jts}


def part_sim(seeds: list, duration: float, motion: str = "xsens") -> dict:
    """Ground truth for (H1)–(H3): a simulated 17-IMU session (benchmarks/body_bench.py set-up: random placements
    ≤ 30°, MEMS noise and bias) whose sensors are ALSO turned about their segment's long (N-pose vertical) axis by
    a uniform random angle in [0°, 360°) — a suit strapped on without regard to the nominal layout — solved with the
    nominal start and with BodyOptions.init "motion" and "auto" (imugraph.body.placement_motion); worst
    joint-angle RMSE and position RMS vs the truth."""
    from benchmarks.body_bench import BLEND_S, NPOSE_S, RATE_HZ, motion_path, sensor_params
    from imugraph.body.evaluate import score_against_truth
    from imugraph.body.placement import Placement
    from imugraph.graphs.body_init import rz
    from imugraph.sim.body import motion_from_bvh, random_placements, simulate_body

    skel, mo = motion_from_bvh(motion_path(motion), rate_hz=RATE_HZ, npose_s=NPOSE_S, blend_s=BLEND_S,
                               duration_s=duration)
    out = {}
    for seed in seeds:
        rng = np.random.default_rng(seed)
        place = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
        yaw = {n: float(rng.uniform(0.0, 2 * np.pi)) for n in place}
        place = {n: Placement(bRs=rz(yaw[n]) @ p.bRs, b_pos=p.b_pos) for n, p in place.items()}
        bs = simulate_body(mo, skel, place, sensor_params(list(place), rng), rng, name=f"{motion}_seed{seed}")
        mask = bs.t >= NPOSE_S + BLEND_S - 1e-9
        row = {}
        for init in ("nominal", "motion", "auto"):
            res, cpu, _ = solve(bs, init=init)
            sc = score_against_truth(res, bs.truth, skel, mask)
            row[init] = {"joint_rmse_max_deg": sc["joint_rmse_max_deg"],
                         "position_rms_cm": 100 * sc["position"]["rms_m"],
                         "cpu_s": cpu, "passes": [q.get("iterations") for q in res.info.get("passes", [])]}
            print(f"sim {motion} seed {seed} ({duration:g} s, sensors turned 0–360° about the long axis), init {init}: "
                  f"worst joint {row[init]['joint_rmse_max_deg']:.2f}°, position RMS "
                  f"{row[init]['position_rms_cm']:.2f} cm, CPU {cpu:.1f} s, LM iterations {row[init]['passes']}")
        out[str(seed)] = row
    return out


def main(argv=None) -> int:
    from imugraph.io.qmt_body import LOWER_BODY_SENSORS, read_qmt_body

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=None, help="only the first S seconds")
    p.add_argument("--lag", type=float, default=1.0, help="fixed-lag smoother lag, s")
    p.add_argument("--no-lag", action="store_true", help="skip the fixed lag")
    p.add_argument("--lag-set", action="append", default=[], metavar="FIELD=VALUE",
                   help="a BodyOptions field for the fixed-lag solve only (helper B23), e.g. lag_init_causal=True")
    p.add_argument("--lower", action="store_true", help="also the 7 lower-body sensors alone")
    p.add_argument("--init", choices=("nominal", "motion", "auto"), default="nominal",
                   help="BodyOptions.init: sensor headings at the start from the nominal placement, or from the motion "
                   "(imugraph.body.placement_motion)")
    p.add_argument("--sim", default="", metavar="SEEDS", help="only the simulated check of motion_placements "
                   "(part_sim) on these seeds, comma-separated")
    p.add_argument("--sim-duration", type=float, default=30.0)
    p.add_argument("--lower-back", default="L5", choices=("L5", "L3"), help="segment of the lower_back sensor")
    p.add_argument("--hinges", default="", help="child segments of hinge joints, comma-separated (e.g. "
                   "RightLowerLeg,LeftLowerLeg: the knees, as mocap --hinges knees)")
    p.add_argument("--npose", default=None, metavar="T0,T1", help="N-pose window in the file's time, s (default: "
                   "detected by the estimator)")
    a = p.parse_args(argv)
    path = data_dir() / FILE
    c0 = time.process_time()
    if a.sim:
        result = {"command": " ".join(sys.argv),
                  "sim": part_sim([int(x) for x in a.sim.split(",")], a.sim_duration)}
        result["cpu_s"] = time.process_time() - c0
        Path("bench_out").mkdir(exist_ok=True)
        (Path("bench_out") / "qmt_full_body_sim.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
        return 0
    bs = read_qmt_body(path, lower_back=a.lower_back)
    read_cpu = time.process_time() - c0
    if a.duration is not None:
        bs = bs.slice(0, int(np.searchsorted(bs.t, bs.t[0] + a.duration)))
    dur = float(bs.t[-1] - bs.t[0])
    result = {"command": " ".join(sys.argv), "file": str(path), "samples": bs.n, "duration_s": dur,
              "read_cpu_s": read_cpu, "read": part_read(bs)}
    npose = None if a.npose is None else tuple(float(x) for x in a.npose.split(","))
    hinges = tuple(h for h in a.hinges.split(",") if h)
    res, cpu, deltas = solve(bs, init=a.init, npose=npose, hinges=hinges)
    if deltas:
        print(f"motion_placements ψ {deltas['_psi_deg']:.1f}°, δ (deg) / (H2) RMS (m/s²):",
              {k: (round(v["delta_deg"]), round(v["rms_m_s2"], 2)) for k, v in deltas.items() if not k.startswith("_")},
              "switched (deg from nominal):", deltas.get("_switched"))
    result["batch"] = {"cpu_s": cpu, "cpu_per_realtime_s": cpu / dur, "npose": res.info.get("npose"),
                       "init": a.init, "motion_placements": deltas,
                       "passes": [{k: v for k, v in q.items() if k in ("iterations", "seconds", "cost_final")}
                                  for q in res.info.get("passes", [])]}
    print(f"\n(e) batch: CPU {cpu:.1f} s for {dur:.1f} s = {cpu / dur:.3f} CPU s per real-time s; N-pose "
          f"{res.info.get('npose')}; LM passes (iterations, final cost) "
          f"{[(q['iterations'], round(q['cost_final'])) for q in result['batch']['passes']]}")
    result["lumbar"] = part_lumbar(res, bs.meta["lower_back"])
    result["plausible"] = part_plausible(res, bs.skeleton)
    result["vs_qmt"] = part_qmt(res, bs)
    result["joint_centres"] = part_joints(res, bs.skeleton)
    if not a.no_lag:
        lag_kw = {k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.lag_set)}
        lag, cpu_l, _ = solve(bs, a.lag, a.init, npose, hinges, lag_kw)
        from imugraph.commands.mocap import timing_summary
        tim = timing_summary(lag.info, dur)
        result["lag"] = {"lag_s": a.lag, "cpu_s": cpu_l, "cpu_per_realtime_s": cpu_l / dur,
                         "timing": {k: v for k, v in tim.items() if k != "bootstrap"},
                         "bootstrap_s": (tim.get("bootstrap") or {}).get("seconds")}
        print(f"\n(e) fixed lag {a.lag:g} s: CPU {cpu_l:.1f} s = {cpu_l / dur:.3f} CPU s per real-time s; "
              f"updates p50 {tim.get('p50_ms', float('nan')):.1f} ms, p99 {tim.get('p99_ms', float('nan')):.1f} ms, "
              f"failed {tim.get('failed_updates')}")
        result["lag"]["plausible"] = part_plausible(lag, bs.skeleton)
        result["batch_vs_lag"] = part_compare(res, lag, bs.skeleton, "(d) batch vs fixed lag")
        result["lag"]["vs_qmt"] = part_qmt(lag, bs)
    if a.lower:
        lb = read_qmt_body(path, sensors=LOWER_BODY_SENSORS)
        if a.duration is not None:
            lb = lb.slice(0, bs.n)
        low, cpu_lo, _ = solve(lb, init=a.init, npose=npose, hinges=hinges)
        result["lower"] = {"cpu_s": cpu_lo, "cpu_per_realtime_s": cpu_lo / dur}
        print(f"\nlower body (7 sensors) batch: CPU {cpu_lo:.1f} s = {cpu_lo / dur:.3f} CPU s per real-time s")
        result["lower"]["plausible"] = part_plausible(low, lb.skeleton)
        result["lower"]["vs_full"] = part_compare(res, low, bs.skeleton, "lower (7) vs full (16) batch", lb.skeleton)
        result["lower"]["vs_qmt"] = part_qmt(low, lb)
    result["cpu_s"] = time.process_time() - c0
    print(f"\ntotal CPU {result['cpu_s']:.1f} s")
    out = Path("bench_out")
    out.mkdir(exist_ok=True)
    (out / "qmt_full_body.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
