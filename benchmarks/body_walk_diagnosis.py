"""Issue 4b diagnosis: where the error of the real walk (gaittoolbox S02-Trial-Walk-1) comes from, joint by joint.

Runs our batch estimator (defaults, no magnetometers, as benchmarks/gaittoolbox_walk.py) and loads Xsens MVN's
output and Vicon; scores both with the "offset" handling of imugraph.body.evaluate.compare_with_vicon at the best
shift, then takes the errors apart (all from the same samples, the 955 Vicon frames):

1. components   per joint and column (flexion, abduction, rotation) the RMSE of ours and MVN, the correlation of
                the two error series, and the RMSE of their difference (an error both IMU systems share comes
                from their common input — the sensors on the body — or from the reference, not from either
                estimator);
2. time         per joint and column: linear trend (deg/s: drift), RMS of the 1 s moving average (slow part)
                and RMS per frequency band, 0–0.4, 0.4–1, 1–2.5, > 2.5 Hz (the stride is ≈ 0.73 Hz here:
                phase-locked errors sit in the 0.4–2.5 Hz bands);
3. segments     per segment the orientation error vs Vicon after the per-segment alignment ("segment" handling:
                R_est ≈ W R_vicon C_s), as a rotation vector in the segment frame: RMS per axis x, y, z (z =
                long axis) for ours and MVN and the correlation of the two z series;
4. rates        per segment the RMS angular rate about its axes: Vicon (finite differences of its quaternions,
                5-sample moving average) vs the RAW gyro turned into our segment frame (a measurement, not an
                estimate) — a mismatch on one side only points at that side's sensor attachment or markers;
5. knee axis    the knee's functional flexion axis from the estimate (principal axis of the thigh–shank
                relative angular rate, in each sensor frame), its angle from the segment y axis of our N-pose
                sensor-to-segment rotation, and the hinge ratio (second/first principal rate; Vicon's too);
6. oracle       the best CONSTANT rotation of the pelvis and/or a thigh frame, fitted on Vicon itself (Nelder–
                Mead on the joint's "offset" RMSE): a lower bound for what any sensor-to-segment calibration
                change could achieve on that joint (not a method: it uses the reference).
7. axial        can a joint set a segment's axial rotation? φ*: the turn of the thigh about its long axis that
                puts its lateral axis on the shank's (what a knee hinge with a soft axial sensor rotation applies,
                imugraph.factors.body_axial), and of the shank onto the foot's, against the axial errors vs Vicon
                (section 3), and the gains of φ* and of those errors on the knee flexion.

    .venv/bin/python benchmarks/body_walk_diagnosis.py [--joints LeftHip,RightHip] [--out body_walk_diagnosis.json]

Writes bench_out/<out>.

Findings (run of the defaults, issue 4b; left hip ours 6.04° vs MVN 5.83°, "offset"):
- the left hip's error is its ROTATION column (ours 9.43°, MVN 8.92°; flexion 3.88 vs 4.34, abduction 2.32 vs
  1.88), shared by both systems (error correlation 0.97, RMS of the difference 2.47°);
- no drift (trend +0.10°/s, 1 s moving average 3.3° RMS): phase-locked (7.2° RMS in 0.4–1 Hz, 5.5° in 1–2.5 Hz;
  peaks of 25–35° in terminal swing, hip flexed ≈ 33° and knee extended);
- it is the left THIGH's axial rotation (segment error about z 9.4° ours, 9.1° MVN, correlation 0.96; pelvis
  1.6°), the left shank's too (10.2°, with the thigh's at correlation 0.72);
- Vicon's left thigh turns about its long axis at 1.68 rad/s RMS, its right thigh at 1.13, while the raw gyros
  give 1.34 and 1.37 (Vicon − gyro RMS about z: left 1.24, right 0.73 rad/s); the IMU-based knees are much less
  hinge-like than Vicon's (second/first principal relative rate 0.5–0.6 vs 0.30–0.35): the thigh sensor and
  the thigh markers disagree about the femur's axial rotation, on the left more than on the right;
- a rigid sensor on a segment between two ball joints cannot see that axis: turning the thigh about the line
  through its hip and knee centres moves neither, so the axial rotation is the integrated gyro whatever the
  body model does (ablation without joints: left hip 6.05°, rotation 9.00°);
- not a calibration error: the functional knee axis agrees with the N-pose thigh y axis to 1.1° (axial), and
  even the best constant left-thigh rotation fitted on Vicon itself only reaches 6.04 → 5.86° (rotation stays
  9.6°); a constant pelvis rotation fitted on Vicon (≈ 20°, the marker pelvis convention) helps both systems
  alike (ours 5.27°, MVN 5.32°);
- no joint can see it either (section 7): the turn that would put the left thigh's lateral axis on the shank's
  (a knee hinge with a soft axial sensor rotation, imugraph.factors.body_axial) is 11.2° RMS but correlates
  −0.15 with the thigh's axial error (right: 9.5°, −0.15); its gain on the knee flexion is −0.15 °/° where the
  thigh error's is +0.34 °/° (right +0.08 vs −0.14); the ankle-implied turn of the shank is 3.0° RMS. The
  thigh and shank axial errors against Vicon both grow with knee flexion (left +0.34, +0.29 °/°): the IMU leg
  and the Vicon leg disagree as a whole about its axial rotation, as a thigh-marker artefact of ≈ 10° (the
  size reported for thigh clusters against fluoroscopy in gait, PMC8631460) would make them.
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

BANDS_HZ = ((0.0, 0.4), (0.4, 1.0), (1.0, 2.5), (2.5, 50.0))
SEGMENTS = ("Pelvis", "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg", "LeftFoot", "RightFoot")


def _rms(x, axis=0):
    return np.sqrt(np.mean(np.square(x), axis=axis))


def time_structure(e: np.ndarray, fs: float) -> dict:
    """Trend, slow part and band RMS of one (T,) error series (mean removed)."""
    e = e - e.mean()
    t = np.arange(e.size) / fs
    trend = np.polyfit(t, e, 1)[0]
    slow = np.convolve(e, np.ones(int(fs)) / int(fs), "same")
    f = np.fft.rfftfreq(e.size, 1.0 / fs)
    P = np.abs(np.fft.rfft(e)) ** 2
    P = P / P.sum() if P.sum() > 0 else P
    bands = {f"{a:g}-{b:g}Hz": float(np.sqrt(P[(f >= a) & (f < b)].sum()) * e.std()) for a, b in BANDS_HZ}
    return {"rms": float(e.std()), "trend_deg_s": float(trend), "slow_1s_rms": float(_rms(slow)), "bands": bands}


def joint_errors(vicon: dict, q: dict, shift: int) -> dict:
    """{joint: (T, 3) angle errors vs Vicon (nominal axis fix), per-column mean removed} at one shift."""
    from imugraph.body.angles import joint_angles
    from imugraph.body.evaluate import LOWER_JOINTS, vicon_joint_angles, wrap_deg
    from imugraph.body.skeleton import lower_body

    skel, idx = lower_body(), np.asarray(vicon["imu_index"])
    a = joint_angles(skel, np.stack([q[s][idx + shift] for s in skel.names], 1))
    ref = vicon_joint_angles(vicon)
    out = {}
    for j in LOWER_JOINTS:
        e = wrap_deg(a[j] - ref[j])
        out[j] = e - e.mean(0)
    return out


def vicon_rotations(vicon: dict) -> dict:
    from imugraph.body.evaluate import VICON_AXES
    from imugraph.geometry import quat_to_rotmat
    return {s: quat_to_rotmat(np.asarray(vicon["quat"][s], float)) @ VICON_AXES.get(s, np.eye(3)) for s in SEGMENTS}


def segment_errors(vicon: dict, q: dict, shift: int) -> tuple[dict, dict]:
    """({segment: (T, 3) rotation vector (deg, segment frame) of (W R_vicon C_s)ᵀ R_est}, {segment: C_s})."""
    from imugraph.body.evaluate import fit_segment_alignment
    from imugraph.geometry import logmap, quat_to_rotmat

    idx = np.asarray(vicon["imu_index"])
    Re = {s: quat_to_rotmat(q[s][idx + shift]) for s in SEGMENTS}
    Rv = vicon_rotations(vicon)
    W, C = fit_segment_alignment(Re, Rv)
    return {s: np.rad2deg(logmap(np.swapaxes(W @ Rv[s] @ C[s], -1, -2) @ Re[s])) for s in SEGMENTS}, C


def rate(R: np.ndarray, fs: float, smooth: int = 1) -> np.ndarray:
    """(T−1, 3) body-frame angular rate of rotations R (T, 3, 3) by finite differences, optional moving average."""
    from imugraph.geometry import logmap
    w = logmap(np.swapaxes(R[:-1], -1, -2) @ R[1:]) * fs
    if smooth > 1:
        k = np.ones(smooth) / smooth
        w = np.stack([np.convolve(w[:, c], k, "same") for c in range(3)], 1)
    return w


def principal_rates(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axes (3, 3) columns by decreasing RMS rate, RMS rates (3,)) of (T, 3) angular rates (PCA)."""
    ev, V = np.linalg.eigh(w.T @ w)
    return V[:, ::-1], np.sqrt(np.maximum(ev[::-1], 0.0) / max(len(w), 1))


def knee_axes(session, res, vicon: dict, fs: float) -> dict:
    """Functional knee flexion axis vs the N-pose segment y axis, and hinge ratios (ours, Vicon)."""
    from imugraph.geometry import quat_to_rotmat

    names = list(res.names)
    out = {}
    for side in ("Left", "Right"):
        P, C = f"{side}UpperLeg", f"{side}LowerLeg"
        rows = {}
        for seg, other in ((P, C), (C, P)):
            bRs = res.placements[seg]["bRs"]
            nRs = quat_to_rotmat(res.n_quat[:, names.index(seg)]) @ bRs          # sensor orientation
            nRo = quat_to_rotmat(res.n_quat[:, names.index(other)]) @ res.placements[other]["bRs"]
            b_seg = np.asarray(res.info["biases"][seg]["gyr"])
            b_oth = np.asarray(res.info["biases"][other]["gyr"])
            w_seg = session.sensors[seg].gyr - b_seg
            w_oth = np.einsum("tji,tjk,tk->ti", nRs, nRo, session.sensors[other].gyr - b_oth)   # in seg's sensor frame
            axes, rates = principal_rates(w_oth - w_seg)                                            # relative rate
            a = bRs @ axes[:, 0]
            a = a if a[1] >= 0 else -a
            rows[seg] = {"axis_in_segment": a.tolist(),
                         "angle_from_y_deg": float(np.rad2deg(np.arccos(np.clip(abs(a[1]), 0.0, 1.0)))),
                         "axial_offset_deg": float(np.rad2deg(np.arctan2(a[0], a[1]))),
                         "hinge_ratio": float(rates[1] / rates[0])}
        Rv = vicon_rotations(vicon)
        _, rv = principal_rates(rate(np.swapaxes(Rv[P], -1, -2) @ Rv[C], fs))
        rows["vicon_hinge_ratio"] = float(rv[1] / rv[0])
        out[f"{side}Knee"] = rows
    return out


def oracle(vicon: dict, q: dict, shift: int, segments: tuple, joints: tuple) -> dict:
    """Best constant rotations c_s (deg) of `segments` (R_s ← R_s Exp(c_s)) for the joints' offset RMSE."""
    from scipy.optimize import minimize

    from imugraph.geometry import expmap, quat_to_rotmat, rotmat_to_quat

    idx = np.asarray(vicon["imu_index"])
    R = {s: quat_to_rotmat(q[s][idx + shift]) for s in SEGMENTS}

    def score(c):
        qq = {s: np.zeros((idx[-1] + shift + 1, 4)) for s in SEGMENTS}
        for s in SEGMENTS:
            Rs = R[s] @ expmap(np.deg2rad(c[3 * segments.index(s): 3 * segments.index(s) + 3])) if s in segments else R[s]
            qq[s][idx + shift] = rotmat_to_quat(Rs)
        e = joint_errors(vicon, qq, shift)
        return {j: _rms(e[j]) for j in joints}

    def cost(c):
        return float(sum(np.mean(np.square(v)) for v in score(c).values()))

    x0 = np.zeros(3 * len(segments))
    simplex = np.vstack([x0] + [x0 + 3.0 * np.eye(x0.size)[i] for i in range(x0.size)])
    r = minimize(cost, x0, method="Nelder-Mead", options={"initial_simplex": simplex, "maxiter": 4000,
                                                            "xatol": 0.01, "fatol": 1e-5})
    before, after = score(x0), score(r.x)
    return {"segments": list(segments), "c_deg": r.x.round(2).tolist(),
            "before": {j: {"cols": v.tolist(), "all": float(_rms(v))} for j, v in before.items()},
            "after": {j: {"cols": v.tolist(), "all": float(_rms(v))} for j, v in after.items()}}


def axial_evidence(vicon: dict, q: dict, shift: int, seg_err: dict) -> dict:
    """Can a joint set the thigh's (or shank's) rotation about its long axis? Per side, on the Vicon frames:
    φ*_knee, the turn of the thigh about its long axis that puts its lateral axis on the shank's (what a knee
    hinge with a soft axial sensor rotation would apply, imugraph.factors.body_axial), and φ*_ankle, the
    same for the shank from the foot; each (mean removed) against the segment's axial error vs Vicon (section
    3), and the gain (deg/deg) of φ*_knee and of the thigh and shank axial errors on the knee flexion."""
    from imugraph.body.angles import joint_angles
    from imugraph.body.skeleton import lower_body
    from imugraph.geometry import quat_to_rotmat

    idx = np.asarray(vicon["imu_index"]) + shift
    skel = lower_body()
    flex = {j: a[:, 0] - a[:, 0].mean() for j, a in joint_angles(skel, np.stack([q[n][idx] for n in skel.names], 1)).items()}

    def turn(P, C):                                  # φ* (deg): about P's z, taking P's y onto C's y
        v = np.einsum("tji,tj->ti", quat_to_rotmat(q[P][idx]), quat_to_rotmat(q[C][idx])[:, :, 1])
        a = np.rad2deg(np.arctan2(-v[:, 0], v[:, 1]))
        return a - a.mean()

    def gain(x, y):
        return float(np.dot(x, y) / np.dot(x, x))

    out = {}
    for side in ("Left", "Right"):
        T, Sh, F = f"{side}UpperLeg", f"{side}LowerLeg", f"{side}Foot"
        ez = {n: seg_err[n][:, 2] - seg_err[n][:, 2].mean() for n in (T, Sh)}
        pk, pa, kf = turn(T, Sh), turn(Sh, F), flex[f"{side}Knee"]
        out[side] = {"knee_turn_rms": float(pk.std()), "corr_knee_turn_thigh_err": float(np.corrcoef(pk, ez[T])[0, 1]),
                     "ankle_turn_rms": float(pa.std()), "corr_ankle_turn_shank_err": float(np.corrcoef(pa, ez[Sh])[0, 1]),
                     "gain_knee_turn_on_flexion": gain(kf, pk), "gain_thigh_err_on_flexion": gain(kf, ez[T]),
                     "gain_shank_err_on_flexion": gain(kf, ez[Sh]),
                     "corr_thigh_err_flexion": float(np.corrcoef(kf, ez[T])[0, 1])}
    return out


def main(argv=None) -> int:
    from benchmarks.gaittoolbox_walk import walk_data, xsens_mvn
    from imugraph.body.evaluate import compare_with_vicon
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions
    from imugraph.io.gaittoolbox import read_gaittoolbox

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--joints", default="LeftHip,RightHip", help="joints for the time/oracle sections")
    ap.add_argument("--out", default="body_walk_diagnosis.json", help="file name in bench_out/")
    a = ap.parse_args(argv)
    data = walk_data()
    if data is None:
        return 1
    root, vicon = data
    fs = float(vicon["fs"])
    session = read_gaittoolbox(root / "rawimu")
    res = solve_body_batch(session, BodyOptions())
    systems = {"ours": {n: res.n_quat[:, i] for i, n in enumerate(res.names)}, "MVN": xsens_mvn(root)}
    shifts = {n: compare_with_vicon(vicon, q, method="offset")["shift_samples"] for n, q in systems.items()}
    E = {n: joint_errors(vicon, q, shifts[n]) for n, q in systems.items()}
    cols = ("flexion", "abduction", "rotation")
    out = {"shifts": shifts, "components": {}, "time": {}, "segments": {}, "rates": {}}
    print(f"1. components (offset handling, shift ours {shifts['ours']} / MVN {shifts['MVN']}), deg")
    for j in E["ours"]:
        row = {}
        for c, col in enumerate(cols):
            eo, em = E["ours"][j][:, c], E["MVN"][j][:, c]
            row[col] = {"ours": float(_rms(eo)), "mvn": float(_rms(em)), "corr": float(np.corrcoef(eo, em)[0, 1]),
                        "diff_rms": float(_rms(eo - em))}
        out["components"][j] = row
        print(f"  {j:11s} " + "  ".join(f"{col[:4]} {v['ours']:5.2f}/{v['mvn']:5.2f} r={v['corr']:.2f} d={v['diff_rms']:.2f}"
                                       for col, v in row.items()))
    print("2. time structure (ours | MVN): rms, trend deg/s, 1 s moving-average rms, bands " +
          ", ".join(f"{lo:g}-{hi:g}" for lo, hi in BANDS_HZ) + " Hz")
    for j in a.joints.split(","):
        out["time"][j] = {}
        for c, col in enumerate(cols):
            ts = {n: time_structure(E[n][j][:, c], fs) for n in systems}
            out["time"][j][col] = ts
            print(f"  {j} {col:9s} " + " | ".join(
                f"{ts[n]['rms']:5.2f} {ts[n]['trend_deg_s']:+.3f} {ts[n]['slow_1s_rms']:4.2f} "
                + " ".join(f"{v:4.2f}" for v in ts[n]["bands"].values()) for n in systems))
    print("3. segment orientation error after per-segment alignment, RMS about x, y, z (deg): ours | MVN | corr z")
    S, C_ours = {}, None
    for n, q in systems.items():
        S[n], C = segment_errors(vicon, q, shifts[n])
        C_ours = C if n == "ours" else C_ours
    for s in SEGMENTS:
        o, m = _rms(S["ours"][s]), _rms(S["MVN"][s])
        r = float(np.corrcoef(S["ours"][s][:, 2], S["MVN"][s][:, 2])[0, 1])
        out["segments"][s] = {"ours": o.tolist(), "mvn": m.tolist(), "corr_z": r}
        print(f"  {s:14s} {o.round(2)} | {m.round(2)} | {r:.2f}")
    print("4. angular rate RMS about the segment axes x, y, z (rad/s): Vicon (finite diff., in our segment axes "
          "by C_s) | raw gyro | RMS of the difference | corr z")
    idx = np.asarray(vicon["imu_index"])
    Rv = vicon_rotations(vicon)
    for s in SEGMENTS:
        wv = rate(Rv[s] @ C_ours[s], fs, smooth=5)                      # body rate of W R_vicon C_s
        g = (session.sensors[s].gyr[idx + shifts["ours"]] @ res.placements[s]["bRs"].T)
        g = np.stack([np.convolve(g[:, c], np.ones(5) / 5, "same") for c in range(3)], 1)[1:]
        r = float(np.corrcoef(wv[:, 2], g[:, 2])[0, 1])
        out["rates"][s] = {"vicon": _rms(wv).tolist(), "gyro": _rms(g).tolist(), "diff": _rms(wv - g).tolist(),
                           "corr_z": r}
        print(f"  {s:14s} {_rms(wv).round(2)} | {_rms(g).round(2)} | {_rms(wv - g).round(2)} | {r:.2f}")
    print("5. knee functional axis (from our estimate) vs the N-pose segment y axis")
    out["knee_axes"] = knee_axes(session, res, vicon, fs)
    for j, rows in out["knee_axes"].items():
        for seg, v in rows.items():
            if isinstance(v, dict):
                print(f"  {j} {seg:14s} axis {np.round(v['axis_in_segment'], 3)}  {v['angle_from_y_deg']:.1f}° from y "
                      f"(axial {v['axial_offset_deg']:+.1f}°), hinge ratio {v['hinge_ratio']:.2f}")
        print(f"  {j} Vicon hinge ratio {rows['vicon_hinge_ratio']:.2f}")
    print("6. oracle: best constant segment rotation fitted on Vicon (lower bound for calibration changes)")
    out["oracle"] = []
    for j in a.joints.split(","):
        thigh = j.replace("Hip", "UpperLeg") if j.endswith("Hip") else None
        for segs in ((("Pelvis",), (thigh,), ("Pelvis", thigh)) if thigh else ()):
            for n in systems:
                o = oracle(vicon, systems[n], shifts[n], segs, (j,))
                o["system"], o["joint"] = n, j
                out["oracle"].append(o)
                print(f"  {n:4s} {j} via {'+'.join(segs):22s} c = {o['c_deg']} deg: {o['before'][j]['all']:.2f} → "
                      f"{o['after'][j]['all']:.2f} (cols {np.round(o['after'][j]['cols'], 2)})")
    print("7. axial evidence (ours): knee/ankle-implied axial turns vs the axial errors; gains on knee flexion")
    out["axial"] = axial_evidence(vicon, systems["ours"], shifts["ours"], S["ours"])
    for side, v in out["axial"].items():
        print(f"  {side}: knee turn {v['knee_turn_rms']:.2f}° rms, corr with thigh axial error "
              f"{v['corr_knee_turn_thigh_err']:+.2f}; ankle turn {v['ankle_turn_rms']:.2f}°, corr with shank "
              f"{v['corr_ankle_turn_shank_err']:+.2f}; gain on knee flexion: knee turn {v['gain_knee_turn_on_flexion']:+.3f}, "
              f"thigh error {v['gain_thigh_err_on_flexion']:+.3f} (corr {v['corr_thigh_err_flexion']:+.2f}), shank error "
              f"{v['gain_shank_err_on_flexion']:+.3f}")
    out["command"] = "benchmarks/body_walk_diagnosis.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(f"\nwrote {write_json(a.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
