"""Issue 4b: the real lower-body walk (gaittoolbox S02-Trial-Walk-1): ours vs Xsens MVN, both scored against Vicon.

Inputs (data directory, nothing copied): gaittoolbox/rawimu (7 Xsens MTw, 100 Hz, 2503 samples, read by
imugraph.io.gaittoolbox.read_gaittoolbox onto lower_body(1.75): nominal proportions, the subject's are not
known), gaittoolbox/xsens/S02-Trial-Walk-1.bvh (Xsens MVN's own output for the same trial: frame k = IMU sample
k, 2503 frames; frame 0 is MVN's T-pose reference, outside the Vicon window), gaittoolbox/vicon/… .csv (Vicon
segment quaternions for IMU samples 1120–2074, 1-based, from data-list.csv).

Ours: `imugraph.graphs.body.solve_body_batch(session, BodyOptions(use_mag=…))` on the whole recording (the
subject stands still for ≈ 10 s first: the N-pose), hip, knee and ankle angles by imugraph.body.angles.

Scoring (imugraph.body.evaluate.compare_with_vicon), the same for both systems, each at its best integer
time shift within ±5 samples; three offset handlings, each stated in the table:
    offset    Vicon feet turned to MVN axes (nominal, VICON_AXES), then per joint and axis the mean difference
              over the window removed (RMSE of what is left);
    segment   per segment a constant alignment C_s (and a world heading W from the pelvis x axes) fitted on
              the whole Vicon window: R_est ≈ W·R_vicon·C_s;
    held-out  the same alignment fitted on the first 5 s of the window only (it includes the turn), scored on
              the remaining 4.55 s.
Per joint: RMSE of flexion/abduction/rotation and "all" (RMS of the three). Target: ours below Xsens MVN on
knee and hip.

    .venv/bin/python benchmarks/gaittoolbox_walk.py [--mag] [--hinges knees] [--axial thighs|shanks|legs|SEGS]
                                                   [--lag S] [--ablation] [--figure] [--skeleton SPEC] [--subsample]
                                                   [--knee-gain thighs|left|SEGS --knee-gain-tau S|none]
                                                   [--init nominal|motion|auto]

--skeleton bvh:mvn reads the session onto the subject's skeleton, from the HIERARCHY (OFFSETs only, never the
motion) of the trial's MVN BVH; also 'height:H' or 'bvh:PATH' (imugraph.body.skeleton.skeleton_from_spec).
Measured 2026-11-23: no change (≤ 0.02° per joint): the lever arms sensor → joint are estimated, their
skeleton-derived priors (σ 7 cm) do not bind (an ad-hoc check of the estimated hip–knee distances, not in
this script, found them equal on either skeleton).
--subsample also scores both systems at their best fractional shift (integer ±5 + 0.1-sample slerp steps).

--knee-gain thighs|left|right|SEGS (session 21, helper H; imugraph.factors.knee_sta, BodyOptions.knee_gain_*): each
thigh sensor turns about the femur's long axis by c_k + g·κ_k (κ the knee flexion, one gain g per thigh from the IMU
data through the knee). --knee-gain-mode graph (needs --hinges knees; c_k, g in the hinge pass) or two-stage (no
hinge pass: least squares on the output's knees); --knee-gain-turn hinge|cardan, --knee-gain-apply gain|offset+gain,
--knee-gain-tau S|none (τ of the slow offset c_k), --knee-gain-screw-home C, --knee-gain-hinge IE,AbAd. Batch only
(the fixed-lag run ignores it). Measured 2026-11-24 (docs/results_issue4.md, session 21 helper H): the best
variant (two-stage, cardan, gain, τ 2 s) gives L hip 5.70° (< MVN 5.83) but the result moves from 5.57° to 6.70°
with τ, and the same estimator on the simulated MVN walk (no soft tissue) finds larger gains and raises its worst
joint from 0.62° to 1.91° (hinge turn: 2.70°, fails 4a): not a default.

--lag S also runs the fixed-lag smoother (imugraph.graphs.body_incremental) and scores it the same way;
--ablation also runs ours without the joint factors and without the lever-arm priors (issue 4c on real data).

Writes bench_out/gaittoolbox_walk.json (and with --figure bench_out/gaittoolbox_walk.png: flexion of hips,
knees and ankles, ours, MVN and Vicon, each with the "offset" handling's constant removed).
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

from benchmarks.common import peak_memory_mb, print_table  # noqa: E402
from benchmarks.output import OUT_DIR, write_json  # noqa: E402
from imugraph.config import data_dir  # noqa: E402

HANDLINGS = {"offset": dict(method="offset"), "segment": dict(method="segment"),
             "held-out": dict(method="segment", align_s=5.0)}
AXIAL_SETS = {"thighs": ("RightUpperLeg", "LeftUpperLeg"), "shanks": ("RightLowerLeg", "LeftLowerLeg"),
              "legs": ("RightUpperLeg", "LeftUpperLeg", "RightLowerLeg", "LeftLowerLeg")}
JOINTS = ("RightHip", "LeftHip", "RightKnee", "LeftKnee", "RightAnkle", "LeftAnkle")


def ours(root: Path, use_mag: bool, hinges: tuple, lag: float | None = None, variant: str = "full", axial: tuple = (),
         skeleton: str | None = None, extra: dict | None = None):
    """({segment: (N, 4)}, info) of our batch (or, with lag, fixed-lag) estimate on the rawimu recording;
    variant: an ablation of benchmarks/body_bench.ablation_options ('full', 'no_joints', 'no_levers'); axial:
    BodyOptions.axial_segments (soft axial sensor-to-segment rotations, seen through the hinges); skeleton: the
    reader's skeleton spec (None: lower_body(1.75); 'bvh:PATH': the subject's, from a BVH hierarchy); extra: more
    BodyOptions fields (e.g. the knee-gain thigh model, imugraph.factors.knee_sta)."""
    from benchmarks.body_bench import ablation_options
    from imugraph.graphs.body import solve_body_batch
    from imugraph.io.gaittoolbox import read_gaittoolbox

    session = read_gaittoolbox(root / "rawimu", skeleton=skeleton)
    opts, _ = ablation_options(variant, use_mag=use_mag, hinges=hinges, **({"axial_segments": axial} if axial else {}),
                               **(extra or {}))
    t0 = time.perf_counter()
    if lag is None:
        res = solve_body_batch(session, opts)
    else:
        from imugraph.graphs.body_incremental import solve_body_incremental
        res = solve_body_incremental(session, opts, lag_s=lag)
    secs = time.perf_counter() - t0
    info = {"seconds": secs, "samples": int(session.n), "npose": res.info.get("npose"),
            "realtime_factor": res.info.get("realtime_factor"),
            "iterations": [p.get("iterations") for p in res.info.get("passes", [])],
            "mag_sigmas": res.info.get("mag_sigmas"), "skeleton": session.meta.get("skeleton"),
            "knee_gain": res.info.get("knee_gain"), "init_motion": res.info.get("init_motion")}
    if lag is None:                 # helper Q22b: the estimated bRs vs the nominal site's (which start was closer)
        from imugraph.geometry import logmap
        from imugraph.graphs.body_model import default_placement
        info["bRs_final_vs_nominal_deg"] = {
            n: round(float(np.degrees(np.linalg.norm(logmap(default_placement(session.skeleton, n)[0].T @ p["bRs"])))), 1)
            for n, p in res.placements.items()}
    return {n: res.n_quat[:, i] for i, n in enumerate(res.names)}, info


def walk_data() -> tuple[Path, dict] | None:
    """(gaittoolbox root, Vicon of S02-Trial-Walk-1) from the data directory; None (message printed) when
    the recordings are absent."""
    from imugraph.io.gaittoolbox import read_gaittoolbox_vicon

    root = data_dir() / "gaittoolbox"
    if not (root / "rawimu").is_dir():
        print(f"{root} absent")
        return None
    return root, read_gaittoolbox_vicon(root / "vicon" / "S02-Trial-Walk-1.csv")


def xsens_mvn(root: Path) -> dict:
    """{segment: (F, 4)} of Xsens MVN's BVH (all frames, frame k = IMU sample k)."""
    from imugraph.body.bvh_map import segment_motion

    skel, _, _, q, _ = segment_motion(root / "xsens" / "S02-Trial-Walk-1.bvh")
    return {n: q[:, i] for i, n in enumerate(skel.names)}


def figure(path: Path, vicon: dict, systems: dict, shifts: dict) -> None:
    """Flexion over the Vicon window, each curve with its own mean offset to Vicon removed."""
    from matplotlib.figure import Figure

    from imugraph.body.angles import joint_angles
    from imugraph.body.evaluate import vicon_joint_angles
    from imugraph.body.skeleton import lower_body
    from imugraph.io.figures import save_figure_atomic

    skel = lower_body()
    idx = np.asarray(vicon["imu_index"])
    ref = vicon_joint_angles(vicon)
    fig = Figure(figsize=(11, 7))
    axes = fig.subplots(3, 2, sharex=True).ravel()
    for ax, j in zip(axes, JOINTS):
        ax.plot(vicon["t"], ref[j][:, 0], "k", lw=1.5, label="Vicon")
        for (name, q), colour in zip(systems.items(), ("tab:red", "tab:blue")):
            a = joint_angles(skel, np.stack([q[n][idx + shifts[name]] for n in skel.names], 1))[j][:, 0]
            ax.plot(vicon["t"], a - np.mean(a - ref[j][:, 0]), color=colour, lw=1.0, label=name)
        ax.set_ylabel(f"{j} flexion (°)", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("t (s, IMU time)")
    fig.suptitle("S02-Trial-Walk-1: flexion, mean offset to Vicon removed")
    fig.tight_layout()
    save_figure_atomic(fig, path)


def fractional(q: dict, f: float) -> dict:
    """{segment: (N, 4)} of `q` delayed by f ∈ [0, 1) samples: q_f[i] = slerp(q[i], q[i+1], f) (last sample held)."""
    from imugraph.geometry import quat_slerp

    out = {}
    for n, a in q.items():
        a = np.asarray(a, float)
        out[n] = quat_slerp(a, np.vstack([a[1:], a[-1:]]), np.full(len(a), f))
    return out


def subsample_table(systems: dict, vicon: dict, step: float = 0.1) -> dict:
    """Each system at its best fractional time shift (integer ±5 of compare_with_vicon + f, f = 0, step, …
    < 1; the same rule for every system), per handling: {handling: {system: compare_with_vicon result +
    "shift_total"}}; printed beside the integer-shift means."""
    from imugraph.body.evaluate import compare_with_vicon

    out, rows = {}, []
    for h, kw in HANDLINGS.items():
        out[h] = {}
        for name, q in systems.items():
            runs = [(f, compare_with_vicon(vicon, fractional(q, f), **kw)) for f in np.arange(0.0, 1.0 - 1e-9, step)]
            f, best = min(runs, key=lambda r: r[1]["mean_all_deg"])
            out[h][name] = dict(best, shift_total=float(best["shift_samples"] + f))
            rows.append([h, name, runs[0][1]["mean_all_deg"], runs[0][1]["joints"]["LeftHip"]["all"],
                         out[h][name]["shift_total"], best["mean_all_deg"]] +
                        [best["joints"][j]["all"] for j in JOINTS])
    print()
    print_table(rows, ["handling", "system", "mean (int)", "L hip (int)", "shift", "mean (frac)"] +
                [f"{j} (frac)" for j in JOINTS])
    return out


def main(argv=None) -> int:
    from imugraph.body.evaluate import compare_with_vicon

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mag", action="store_true", help="our estimator with magnetometers")
    ap.add_argument("--hinges", default="", help="comma-separated hinge child segments, or 'knees'")
    ap.add_argument("--axial", default="", help="segments with a soft axial sensor rotation (comma-separated, or "
                    "'thighs', 'shanks', 'legs'); needs --hinges")
    ap.add_argument("--lag", type=float, default=None, help="also score the fixed-lag estimate with this lag, s")
    ap.add_argument("--ablation", action="store_true", help="also our estimate without joints / lever priors")
    ap.add_argument("--skeleton", default="nominal", help="our skeleton: 'nominal' (lower_body(1.75)), 'height:H', "
                    "'bvh:PATH' or 'bvh:mvn' (the subject's, from the hierarchy of the trial's MVN BVH; its "
                    "motion unused)")
    ap.add_argument("--subsample", action="store_true", help="also score both systems at their best fractional "
                    "shift (0.1-sample slerp steps on top of the integer search)")
    ap.add_argument("--knee-gain", default="", help="thighs whose sensor turns about the long axis by c_k + g·κ_k "
                    "(imugraph.factors.knee_sta; comma-separated, 'thighs' or 'left'); needs --hinges knees")
    ap.add_argument("--knee-gain-tau", default="2", help="τ_c of the offset c_k, s, or 'none' (one constant)")
    ap.add_argument("--knee-gain-sigma", type=float, default=0.5, help="prior σ of the gain g, rad/rad")
    ap.add_argument("--knee-gain-mode", choices=("graph", "two-stage"), default="graph",
                    help="BodyOptions.knee_gain_mode (two-stage needs no --hinges)")
    ap.add_argument("--knee-gain-apply", choices=("offset+gain", "gain"), default="offset+gain",
                    help="BodyOptions.knee_gain_apply")
    ap.add_argument("--knee-gain-screw-home", type=float, default=0.0, help="BodyOptions.knee_gain_screw_home, rad/rad")
    ap.add_argument("--knee-gain-turn", choices=("hinge", "cardan"), default="hinge", help="BodyOptions.knee_gain_turn")
    ap.add_argument("--knee-gain-hinge", default="", help="σ of that knee's hinge (S3), 'IE,AbAd' rad (default: "
                    "BodyOptions.axial_hinge_sigmas_rad)")
    ap.add_argument("--init", choices=("nominal", "motion", "auto"), default="nominal", help="BodyOptions.init (helper Q22b): sensor headings from the nominal placement or from the motion (imugraph.body.placement_motion)")
    ap.add_argument("--lag-set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a BodyOptions field for the fixed-lag solve only (helper B23), e.g. lag_init_causal=True")
    ap.add_argument("--figure", action="store_true")
    ap.add_argument("--out", default="gaittoolbox_walk.json", help="file name in bench_out/")
    a = ap.parse_args(argv)
    data = walk_data()
    if data is None:
        return 1
    root, vicon = data
    hinges = ("RightLowerLeg", "LeftLowerLeg") if a.hinges == "knees" else tuple(h for h in a.hinges.split(",") if h)
    axial = AXIAL_SETS.get(a.axial, tuple(x for x in a.axial.split(",") if x))
    skeleton = f"bvh:{root / 'xsens' / 'S02-Trial-Walk-1.bvh'}" if a.skeleton == "bvh:mvn" else a.skeleton
    kg = {"thighs": AXIAL_SETS["thighs"], "left": ("LeftUpperLeg",), "right": ("RightUpperLeg",)}.get(
        a.knee_gain, tuple(x for x in a.knee_gain.split(",") if x))
    kg_opts = {"knee_gain_segments": kg, "knee_gain_sigma": a.knee_gain_sigma,
             "knee_gain_offset_tau_s": None if a.knee_gain_tau == "none" else float(a.knee_gain_tau),
             "knee_gain_mode": a.knee_gain_mode, "knee_gain_apply": a.knee_gain_apply,
             "knee_gain_screw_home": a.knee_gain_screw_home, "knee_gain_turn": a.knee_gain_turn,
             "knee_gain_hinge_sigmas_rad": tuple(float(v) for v in a.knee_gain_hinge.split(",")) if a.knee_gain_hinge
             else None} if kg else {}
    init_kw = {"init": a.init} if a.init != "nominal" else {}     # helper Q22b: BodyOptions.init, every solve
    q_ours, info = ours(root, a.mag, hinges, axial=axial, skeleton=skeleton, extra={**kg_opts, **init_kw})
    if info.get("knee_gain"):
        print("knee gain: " + ", ".join(f"{n} g {v['gain']:+.3f}, offset sd {np.rad2deg(v['offset_std_rad']):.2f}°"
                                        for n, v in info["knee_gain"].items()))
    info["skeleton_stated"] = ("subject's, from the MVN BVH hierarchy" if a.skeleton == "bvh:mvn" else info["skeleton"])
    print(f"skeleton: {info['skeleton_stated']}")
    print("estimated bRs vs the nominal site's (deg):", info.get("bRs_final_vs_nominal_deg"))
    if info.get("init_motion"):
        print("init motion (H3) δ / (H4) ψ, switched (deg from nominal):",
              {k: v["delta_deg"] for k, v in info["init_motion"].items() if not k.startswith("_")},
              info["init_motion"].get("_psi_deg"), info["init_motion"].get("_switched"))
    print(f"ours: {info['samples']} samples solved in {info['seconds']:.1f} s (npose {info['npose']}, "
          f"LM iterations {info['iterations']})")
    systems = {"ours": q_ours, "Xsens MVN": xsens_mvn(root)}
    for variant in (("no_joints", "no_levers") if a.ablation else ()):
        systems[f"ours {variant}"], info[variant] = ours(root, a.mag, hinges, None, variant, axial, skeleton,
                                                          {**kg_opts, **init_kw})
        print(f"ours {variant}: {info[variant]['seconds']:.1f} s")
    if a.lag is not None:
        try:
            import ast
            lag_kw = {k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.lag_set)}
            q_lag, info["fixed_lag"] = ours(root, a.mag, hinges, a.lag, axial=axial, skeleton=skeleton,
                                            extra={**init_kw, **lag_kw})
            systems[f"ours lag {a.lag:g} s"] = q_lag
            print(f"ours, fixed lag {a.lag:g} s: {info['fixed_lag']['seconds']:.1f} s")
        except Exception as exc:              # report the failure of the incremental solver, score the rest
            info["fixed_lag"] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"ours, fixed lag {a.lag:g} s: failed ({info['fixed_lag']['error'][:160]})")
    results = {h: {name: compare_with_vicon(vicon, q, **kw) for name, q in systems.items()}
               for h, kw in HANDLINGS.items()}
    rows = []
    lag_name = next((n for n in systems if n.startswith("ours lag")), None)
    for h, res in results.items():
        for j in JOINTS:
            o, m = res["ours"]["joints"][j], res["Xsens MVN"]["joints"][j]
            extra = [res[lag_name]["joints"][j]["all"]] if lag_name else []
            rows.append([h, j, o["flexion"], m["flexion"], o["all"], m["all"]] + extra +
                        ["ours" if o["all"] < m["all"] else "MVN"])
        extra = [res[lag_name]["mean_all_deg"]] if lag_name else []
        rows.append([h, "mean", np.mean([res["ours"]["joints"][j]["flexion"] for j in JOINTS]),
                     np.mean([res["Xsens MVN"]["joints"][j]["flexion"] for j in JOINTS]),
                     res["ours"]["mean_all_deg"], res["Xsens MVN"]["mean_all_deg"]] + extra +
                    [f"shift {res['ours']['shift_samples']}/{res['Xsens MVN']['shift_samples']}"])
    print_table(rows, ["handling", "joint", "flex ours", "flex MVN", "all ours", "all MVN"] +
                (["all lag"] if lag_name else []) + ["lower (all)"])
    others = [n for n in systems if n not in ("ours", "Xsens MVN")]
    if others:
        print()
        print_table([[h, j] + [results[h][n]["joints"][j]["all"] for n in ["ours", "Xsens MVN"] + others]
                     for h in results for j in JOINTS + ("mean",) if j != "mean"] +
                    [[h, "mean"] + [results[h][n]["mean_all_deg"] for n in ["ours", "Xsens MVN"] + others]
                     for h in results], ["handling", "joint (all, °)", "ours", "Xsens MVN"] + others)
    if a.subsample:
        results["subsample"] = subsample_table({n: q for n, q in systems.items() if n in ("ours", "Xsens MVN")}, vicon)
    if a.figure:
        shown = {n: q for n, q in systems.items() if n in ("ours", "Xsens MVN")}
        shifts = {n: results["offset"][n]["shift_samples"] for n in shown}
        figure(OUT_DIR / "gaittoolbox_walk.png", vicon, shown, shifts)
    payload = {"issue": "4b", "use_mag": a.mag, "init": a.init, "skeleton": skeleton or "nominal",
               "hinges": list(hinges), "axial_segments": list(axial), "knee_gain": kg_opts,   # tuples: json_ready
               "ours": info, "handlings": HANDLINGS,
               "results": results, "peak_memory_mb": peak_memory_mb(),
               "command": "benchmarks/gaittoolbox_walk.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    print(f"\nwrote {write_json(a.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
