"""Issue 4b, session 21 (helper H): can a knee-flexion-proportional thigh-sensor turn, estimated from the IMU data,
take the real walk's left hip below Xsens MVN's?

Hypothesis (docs/results_issue4.md §b, benchmarks/body_walk_diagnosis.py §7): the thigh's axial error against Vicon
grows with knee flexion (+0.34 °/° left). A soft-tissue model with one gain per thigh,

    nR_thigh(t) = nR_thigh,rigid(t) · Exp(g · κ(t) ẑ)                                               (H1)

(κ the knee flexion, ẑ the thigh's long axis), could remove that part if g can be read from the IMU data. The only
IMU-side signal about the thigh's axial rotation is the knee: the turn φ*(t) about the thigh's z that puts its
lateral axis on the shank's (a hinge knee). g is fitted WITHOUT Vicon as the least-squares slope of φ* on κ
over the whole recording after the N-pose (our estimate only):

    g = Σ (κ − κ̄)(φ* − φ̄*) / Σ (κ − κ̄)²                                                          (H2)

and (H1) is applied to the batch output (a post-processing stand-in for the graph model: what the hinge (S3) of
imugraph.factors.body_axial would impose if θ = c + g κ). Also printed, as DIAGNOSTICS that use Vicon (never a
method): the left-hip error of both systems by gait phase (knee flexion terciles, ours) and column, and the
left-hip "all" RMSE over a sweep of g (what gain the reference would want).

    .venv/bin/python benchmarks/h21_thigh_gain.py [--out h21_thigh_gain.json]

Writes bench_out/<out>.

Findings (2026-11-24, defaults, offset handling): the left hip's extra error over MVN is in its rotation and
abduction columns in every knee-flexion tercile (rotation ours/MVN 10.39/9.92, 6.77/6.65, 10.61/9.77°; abduction
2.66/2.09, 2.21/1.83, 2.04/1.71°; flexion is ours' better in all three). (H2) over the whole recording gives
g = +0.05 (left), −0.15 (right): the 10 s standing before the walk pulls it; on walking windows −0.07…−0.19 (left);
on rates −0.047 / −0.056, high-passed −0.072 / −0.022. Vicon itself would want g ≈ −0.25…−0.3 on the left (sweep,
section 4). Applied post hoc: whole-recording g → L hip 6.43°; rates → 5.70° but R hip 3.51° (+0.36);
high-passed → 5.54°, R hip 3.28°. A literature screw-home knee (c 0.1 °/°) turns the left g to +0.15 (L hip
7.28°). The left thigh alone delayed by −3…+3 samples: 6.05–6.34°, never below 6.04° (no clock offset).
Knee internal rotation per flexion (Vicon window): Vicon +0.094 / +0.194 (left / right), ours +0.028 / −0.000,
MVN −0.141 / +0.133.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.output import write_json  # noqa: E402

JOINTS = ("RightHip", "LeftHip", "RightKnee", "LeftKnee", "RightAnkle", "LeftAnkle")


def knee_turn(q: dict, thigh: str, shank: str) -> np.ndarray:
    """(N,) φ* (deg): the turn about the thigh's z that takes its y axis onto the shank's y (φ* = atan2(−v_x, v_y),
    v the shank's y in the thigh frame)."""
    from imugraph.geometry import quat_to_rotmat

    v = np.einsum("tji,tj->ti", quat_to_rotmat(q[thigh]), quat_to_rotmat(q[shank])[:, :, 1])
    return np.rad2deg(np.arctan2(-v[:, 0], v[:, 1]))


def knee_flexion(q: dict, side: str) -> np.ndarray:
    from imugraph.body.angles import joint_angles
    from imugraph.body.skeleton import lower_body

    skel = lower_body()
    return joint_angles(skel, np.stack([q[n] for n in skel.names], 1))[f"{side}Knee"][:, 0]


def turned(q: dict, seg: str, ang_deg: np.ndarray) -> dict:
    """Copy of q with segment `seg` turned about its own z by ang_deg(t) (H1)."""
    from imugraph.geometry import quat_to_rotmat, rotmat_to_quat

    a = np.deg2rad(ang_deg)
    Rz = np.zeros((a.size, 3, 3))
    Rz[:, 0, 0] = Rz[:, 1, 1] = np.cos(a)
    Rz[:, 0, 1], Rz[:, 1, 0] = -np.sin(a), np.sin(a)
    Rz[:, 2, 2] = 1.0
    out = dict(q)
    out[seg] = rotmat_to_quat(quat_to_rotmat(q[seg]) @ Rz)
    return out


def slope(x: np.ndarray, y: np.ndarray) -> float:
    """(H2) least-squares slope of y on x, means removed."""
    x, y = x - x.mean(), y - y.mean()
    return float(np.dot(x, y) / np.dot(x, x))


def phase_table(vicon: dict, systems: dict, kappa: np.ndarray, shifts: dict) -> dict:
    """Left-hip error (offset handling: column means removed) by terciles of OUR left knee flexion (IMU-only
    phase variable), per column, both systems (a diagnostic: uses Vicon)."""
    from benchmarks.body_walk_diagnosis import joint_errors

    idx = np.asarray(vicon["imu_index"])
    k = kappa[idx + shifts["ours"]]
    edges = np.quantile(k, [0, 1 / 3, 2 / 3, 1])
    out = {}
    for name, q in systems.items():
        e = joint_errors(vicon, q, shifts[name])["LeftHip"]
        rows = {}
        for b in range(3):
            m = (k >= edges[b]) & (k <= edges[b + 1])
            rows[f"knee {edges[b]:.0f}-{edges[b + 1]:.0f} deg"] = np.sqrt(np.mean(e[m] ** 2, 0)).round(2).tolist()
        rows["all"] = np.sqrt(np.mean(e ** 2, 0)).round(2).tolist()
        out[name] = rows
    return out


def main(argv=None) -> int:
    from benchmarks.gaittoolbox_walk import walk_data, xsens_mvn
    from imugraph.body.evaluate import compare_with_vicon
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions
    from imugraph.io.gaittoolbox import read_gaittoolbox

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="h21_thigh_gain.json")
    a = ap.parse_args(argv)
    data = walk_data()
    if data is None:
        return 1
    root, vicon = data
    session = read_gaittoolbox(root / "rawimu")
    res = solve_body_batch(session, BodyOptions())
    from imugraph.graphs.body_model import npose_samples
    npose = int(npose_samples(session, BodyOptions())[0][-1]) + 1          # first sample after the N-pose
    q = {n: res.n_quat[:, i] for i, n in enumerate(res.names)}
    mvn = xsens_mvn(root)
    base = {"ours": compare_with_vicon(vicon, q, method="offset"), "MVN": compare_with_vicon(vicon, mvn, method="offset")}
    shifts = {n: r["shift_samples"] for n, r in base.items()}
    out = {"npose": npose, "base": {n: {j: r["joints"][j] for j in JOINTS} | {"mean": r["mean_all_deg"]}
                                    for n, r in base.items()}}
    print("1. left hip by gait phase (terciles of our left knee flexion), RMSE flexion/abduction/rotation, deg")
    kappa = {s: knee_flexion(q, s) for s in ("Left", "Right")}
    out["phase"] = phase_table(vicon, {"ours": q, "MVN": mvn}, kappa["Left"], shifts)
    for name, rows in out["phase"].items():
        for b, v in rows.items():
            print(f"  {name:5s} {b:18s} {v}")
    print("2. gain g (H2) of the knee-implied thigh turn φ* on the knee flexion, from our estimate after the N-pose")
    use = np.arange(res.n_quat.shape[0]) >= npose
    phi_all = {s: knee_turn(q, f"{s}UpperLeg", f"{s}LowerLeg") for s in ("Left", "Right")}     # φ* every sample
    gains = {}
    for s in ("Left", "Right"):
        phi = phi_all[s]
        gains[s] = slope(kappa[s][use], phi[use])
        print(f"  {s}: g = {gains[s]:+.3f} deg/deg (φ* RMS {phi[use].std():.2f}°, knee flexion RMS {kappa[s][use].std():.2f}°)")
    out["gains"] = gains
    # the same slope on windows of the recording (IMU samples; the Vicon window is only used to name the window)
    idx0, idx1 = int(vicon["imu_index"][0]), int(vicon["imu_index"][-1])
    from imugraph.geometry import quat_to_rotmat
    yaw = np.rad2deg(np.unwrap(np.arctan2(*quat_to_rotmat(q["Pelvis"])[:, 1::-1, 0].T)))
    out["gain_windows"] = {}
    wins = [("after N-pose, before Vicon", npose, idx0), ("Vicon window", idx0, idx1 + 1), ("after Vicon", idx1 + 1, len(yaw))]
    wins += [(f"{i0}-{i0 + 200}", i0, i0 + 200) for i0 in range(npose, len(yaw) - 199, 200)]
    for name, i0, i1 in wins:
        sl = slice(i0, i1)
        row = {s: slope(kappa[s][sl], phi_all[s][sl]) for s in ("Left", "Right")}
        row |= {"knee_rms": float(kappa["Left"][sl].std()), "pelvis_yaw_change": float(yaw[i1 - 1] - yaw[i0])}
        out["gain_windows"][name] = row
        print(f"  {name:28s} g left {row['Left']:+.3f} right {row['Right']:+.3f}  (left knee flexion RMS "
              f"{row['knee_rms']:.1f}°, pelvis heading change {row['pelvis_yaw_change']:+.0f}°)")
    # (H2') the slope free of the offset c: on the rates (H2 of the first differences, 5-sample moving average),
    # and on the high-passed series (1 s moving average removed): standing still no longer pulls on g
    fs = 1.0 / float(np.median(np.diff(session.t)))
    phis = {s: phi_all[s][use] for s in ("Left", "Right")}
    smooth = lambda x, n: np.convolve(x, np.ones(n) / n, "same")          # noqa: E731
    g_rate = {s: slope(smooth(np.diff(kappa[s][use]), 5), smooth(np.diff(phis[s]), 5)) for s in phis}
    g_hp = {s: slope(kappa[s][use] - smooth(kappa[s][use], int(fs)), phis[s] - smooth(phis[s], int(fs))) for s in phis}
    out["gains_rate"], out["gains_highpass"] = g_rate, g_hp
    print(f"  (H2') on rates: left {g_rate['Left']:+.3f} right {g_rate['Right']:+.3f}; high-passed (1 s): left "
          f"{g_hp['Left']:+.3f} right {g_hp['Right']:+.3f}")
    print("3. (H1) applied with the IMU-estimated g: offset-handling RMSE 'all' per joint, deg")

    def both(g):
        return turned(turned(q, "LeftUpperLeg", g["Left"] * kappa["Left"]), "RightUpperLeg", g["Right"] * kappa["Right"])
    variants = {"ours": q, "left thigh g": turned(q, "LeftUpperLeg", gains["Left"] * kappa["Left"]),
                "both thighs g": both(gains), "both g rate": both(g_rate), "both g highpass": both(g_hp),
                "left g rate": turned(q, "LeftUpperLeg", g_rate["Left"] * kappa["Left"]), "MVN": mvn}
    out["variants"] = {}
    for name, qq in variants.items():
        r = compare_with_vicon(vicon, qq, method="offset")
        lh = r["joints"]["LeftHip"]
        out["variants"][name] = {j: r["joints"][j]["all"] for j in JOINTS} | {
            "mean": r["mean_all_deg"], "LeftHip_cols": [lh[c] for c in ("flexion", "abduction", "rotation")]}
        print(f"  {name:14s} " + " ".join(f"{j} {r['joints'][j]['all']:.2f}" for j in JOINTS) + f"  mean {r['mean_all_deg']:.2f}")
    print("4. DIAGNOSTIC (uses Vicon): left hip / left knee 'all' over a sweep of the left-thigh gain g")
    out["sweep"] = {}
    for g in (-0.4, -0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3):
        r = compare_with_vicon(vicon, turned(q, "LeftUpperLeg", g * kappa["Left"]), method="offset")
        out["sweep"][g] = {j: r["joints"][j]["all"] for j in ("LeftHip", "LeftKnee")}
        print(f"  g {g:+.1f}: LeftHip {r['joints']['LeftHip']['all']:.2f}  LeftKnee {r['joints']['LeftKnee']['all']:.2f}")
    print("5. knee rotation vs flexion (slope, deg/deg, Vicon window; ISB signs: rotation > 0 internal): the knee's "
          "screw-home coupling as each system sees it, and (H2) corrected by a literature screw-home knee")
    from imugraph.body.evaluate import vicon_joint_angles
    from imugraph.body.angles import joint_angles
    from imugraph.body.skeleton import lower_body
    idx = np.asarray(vicon["imu_index"])
    ref = vicon_joint_angles(vicon)
    out["knee_coupling"] = {}
    for s in ("Left", "Right"):
        row = {"vicon": slope(ref[f"{s}Knee"][:, 0], ref[f"{s}Knee"][:, 2])}
        for name, qq in (("ours", q), ("MVN", mvn)):
            ang = joint_angles(lower_body(), np.stack([qq[n][idx + shifts[name]] for n in lower_body().names], 1))[f"{s}Knee"]
            row[name] = slope(ang[:, 0], ang[:, 2])
        out["knee_coupling"][s] = row
        print(f"  {s}Knee: " + "  ".join(f"{k} {v:+.3f}" for k, v in row.items()))
    # screw-home knee, internal tibial rotation c·κ (c = 0.1 °/°: ≈ 9° over 0–90°, literature): the hinge then asks
    # the thigh to turn by φ* + c κ (left) / φ* − c κ (right) (φ* ≈ −(knee rotation) left, + right)
    c_sh = 0.1
    g_sh = {"Left": gains["Left"] + c_sh, "Right": gains["Right"] - c_sh}
    r = compare_with_vicon(vicon, turned(q, "LeftUpperLeg", g_sh["Left"] * kappa["Left"]), method="offset")
    out["screw_home"] = {"c": c_sh, "g": g_sh, "joints": {j: r["joints"][j]["all"] for j in JOINTS}}
    print(f"  screw-home c {c_sh}: g left {g_sh['Left']:+.3f} → LeftHip {r['joints']['LeftHip']['all']:.2f} "
          f"LeftKnee {r['joints']['LeftKnee']['all']:.2f}")
    print("6. DIAGNOSTIC (uses Vicon): the left thigh alone delayed by d samples (a per-sensor clock offset)")
    out["thigh_shift"] = {}
    for d in (-3, -2, -1, 1, 2, 3):
        qq = dict(q)
        qq["LeftUpperLeg"] = np.roll(q["LeftUpperLeg"], d, axis=0)
        r = compare_with_vicon(vicon, qq, method="offset")
        out["thigh_shift"][d] = {j: r["joints"][j]["all"] for j in ("LeftHip", "LeftKnee")}
        print(f"  d {d:+d}: LeftHip {r['joints']['LeftHip']['all']:.2f}  LeftKnee {r['joints']['LeftKnee']['all']:.2f}")
    out["command"] = "benchmarks/h21_thigh_gain.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(f"\nwrote {write_json(a.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
