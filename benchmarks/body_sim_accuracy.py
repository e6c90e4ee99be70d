"""Issue 4a: body mocap accuracy on 17-IMU sessions simulated from real motions, without and with magnetometers.

For each motion (CMU 131_01, 131_02 and the gaittoolbox Xsens MVN BVH; see benchmarks/body_bench.py for the
N-pose, the random sensor placements and the sensor errors) and each seed, the batch estimator
`imugraph.graphs.body.solve_body_batch` runs with BodyOptions(use_mag=False) and (use_mag=True); scores:
joint-angle RMSE per joint (imugraph.body.evaluate eq. E1: per joint the RMS over flexion, abduction and
rotation; the per-column values are in the JSON) and the relative segment position error (eq. E2: segment
origins relative to the pelvis, best constant heading removed), over the BVH motion only.
Targets: ≤ 2° per joint, ≤ 2 cm.

    .venv/bin/python benchmarks/body_sim_accuracy.py [--motions cmu131_01,cmu131_02,xsens] [--seeds 0]
        [--duration S] [--lower] [--mag both|off|on] [--lag S] [--tie] [--bias-walk SIGMA]
        [--hinges knees] [--axial shanks|thighs|legs] [--unsensed SIGMA_DEG[,SIGMA_DEG…]]
        [--unsensed-prior fixed|shared] [--unsensed-chains Head] [--unsensed-npose-sigma DEG]
        [--unsensed-gain G] [--neck tie,bend,lever,bend+lever]

--duration limits the BVH time used (after the Xsens export's T-pose frame); --lower simulates the 7-sensor
lower body only (quick runs); --tie makes the truth's unsensed segments (spine links, neck, toes) follow
the estimator's ties instead of the BVH (isolates the estimator from that model error); --lag S also runs
the fixed-lag smoother (imugraph.graphs.body_incremental; --lag-bootstrap S: its batch bootstrap in s instead of
"auto"; --neck lagboot: BodyOptions.lag_neck_from_bootstrap, the neck's bend (N5) from that bootstrap); --unsensed σ models the unsensed links between two
sensed segments (neck, lumbar spine) as estimated segments with σ (degrees) per joint on their shared relative
rotation (BodyOptions.unsensed_sigma_rad, imugraph.graphs.body_chain; batch only); several comma-separated
values, or "off" among them (the default model), each solve the same simulated session; --unsensed-prior and
--unsensed-chains set BodyOptions.unsensed_prior and unsensed_chains (e.g. "Head": the neck only),
--unsensed-npose-sigma BodyOptions.unsensed_npose_sigma_rad (in degrees), --unsensed-gain
BodyOptions.unsensed_sigma_gain. With several seeds a second table gives, per motion
and magnetometer setting, the worst joint and position over the seeds (`seed_summary`). --neck (session 21,
imugraph.graphs.body_neck): comma-separated variants, each solving the same simulated session: "default" (the
default model, since session 21 = "bend+lumped1"), "tie" (the default before session 21: (K2) ties), "bend" (BodyOptions.unsensed_bend=("Head",): the neck turned with T8 by the bend the graph's
levers imply, N5), "lever" (lever_prior_frame="estimated": a second pass with the lever priors in the
estimated sensor frames, N6), "bend+lever" (both), "bend+lumped" (N6 for the lumped joints' levers only),
"bend+lumped5" (the same with lever_pass_lumped_sigma_m 5 mm), "bend+lumped1" (lever_pass_iterations 1);
helper N21b: "len" (the default + BodyOptions.unsensed_bend_length_sigma_m 5 mm, body_neck (N7)), "lumped10" /
"lumped7" / "lumped5" (the default with lumped_joint_sigma_m 10 / 7.5 / 5 mm in both passes), "neck5" / "neck7"
(BodyOptions.lever_pass_bend_sigma_m 5 / 7.5 mm: only the neck's lumped joint, only in the (N6) pass, body_neck
(N8), that pass run to convergence), "mf" / "neck5mf" (BodyOptions.unsensed_bend_mag_free, body_neck (N9): with
magnetometers the bend read from the (N6) graph solved without them; alone / with neck5), "neck3mf" (N8 3 mm + N9);
labels and the seed table carry the variant.
Helper Q22b: --neck motion = the default with BodyOptions.init "motion" (sensor headings from the joint
accelerations, imugraph.body.placement_motion), --neck auto = init "auto" (motion only for sensors > 45° from
nominal); compare with --neck default,motion,auto.
Helper L22 (the fixed lag's own neck bend and bootstrap; imugraph.graphs.body_lag_neck, body_lag_settle): --neck
"lagstream[NN]" (BodyOptions.lag_neck_stream, neck-lever anchor σ NN mm), "ovN" (lag_bootstrap_overlap_s N s), "bsN" /
"ls20bsN" / "lsmargbsN" ((A1) thresholds × N), "marg" / "lsmarg" (lag_bootstrap_marginal), "lsmargsetN" / "ls20setN"
(lag_bootstrap_settle_deg 0.N°), "lsmargset3mo" / "lsmargbs3mo" (+ lag_neck_mag_offset); --lag-only skips the batch solves,
--lag-iterations sets solve_body_incremental's lag_iterations, --lag-filtered also scores the lag's filtered output
(label "… filtered"); records carry the bootstrap length (bootstrap_s).
Writes bench_out/body_sim_accuracy.json.
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

from benchmarks.body_bench import (MOTIONS, NOISE, SUMMARY_COLUMNS, motion_path, simulated_session,  # noqa: E402
                                   summary_row)
from benchmarks.common import peak_memory_mb, print_table  # noqa: E402
from benchmarks.output import write_json  # noqa: E402


def _solve(session, use_mag: bool, lag: float | None, opts_kw: dict | None = None):
    from imugraph.graphs.body import solve_body_batch
    from imugraph.graphs.body_model import BodyOptions

    opts = BodyOptions(use_mag=use_mag, **(opts_kw or {}))
    if lag is None:
        return solve_body_batch(session, opts)
    from imugraph.graphs.body_incremental import solve_body_incremental
    return solve_body_incremental(session, opts, lag_s=lag, **_LAG_KW)


_LAG_KW: dict = {}          # --lag-bootstrap S (helper L21): solve_body_incremental's bootstrap_s; {}: its "auto"
_FILTERED: list = []        # --lag-filtered (helper L22): also score the fixed lag's filtered output (info["filtered"])


# --neck variants (session 21): BodyOptions fields of imugraph.graphs.body_neck (N5), (N6)
_TIES = {"unsensed_bend": (), "lever_prior_frame": "nominal", "lever_pass_iterations": None,
         "lever_pass_bend_sigma_m": None, "unsensed_bend_mag_free": False}
_S21A = {"unsensed_bend": ("Head",), "lever_prior_frame": "lumped", "lever_pass_iterations": 1,     # the default
         "lever_pass_bend_sigma_m": None, "unsensed_bend_mag_free": False}                           # of a3049c8
NECK_VARIANTS = {"default": {},                                  # since session 21's second flip = "neck5mf"
                 "tie": _TIES,                                   # the default before session 21
                 "motion": {"init": "motion"},                   # helper Q22b: BodyOptions.init (placement_motion)
                 "auto": {"init": "auto"},                       # helper Q22b: motion only where > 45° from nominal
                 "bend": {**_TIES, "unsensed_bend": ("Head",)}, "lever": {**_TIES, "lever_prior_frame": "estimated"},
                 "bend+lever": {**_TIES, "unsensed_bend": ("Head",), "lever_prior_frame": "estimated"},
                 "bend+lumped": {**_TIES, "unsensed_bend": ("Head",), "lever_prior_frame": "lumped"},
                 "bend+lumped5": {**_TIES, "unsensed_bend": ("Head",), "lever_prior_frame": "lumped",
                                  "lever_pass_lumped_sigma_m": 0.005},
                 "bend+lumped1": _S21A,
                 # session 21, helper N21b (on top of bend+lumped1, the default then): (N7) the neck-length factor in
                 # the (N6) pass; the lumped joints' σ (both passes) 10 / 7.5 mm instead of 20 mm
                 "len": {**_S21A, "unsensed_bend_length_sigma_m": 0.005},
                 "lumped10": {**_S21A, "lumped_joint_sigma_m": 0.01}, "lumped7": {**_S21A, "lumped_joint_sigma_m": 0.0075},
                 "lumped5": {**_S21A, "lumped_joint_sigma_m": 0.005},
                 # (N8): only the neck's lumped joint tighter, in the (N6) pass (LM to convergence there)
                 "neck5": {**_S21A, "lever_pass_bend_sigma_m": 0.005, "lever_pass_iterations": None},
                 "neck7": {**_S21A, "lever_pass_bend_sigma_m": 0.0075, "lever_pass_iterations": None},
                 # (N9): with magnetometers, the bend read from the (N6) graph without them (on top of neck5 / alone)
                 "neck5mf": {**_S21A, "lever_pass_bend_sigma_m": 0.005, "lever_pass_iterations": None,
                             "unsensed_bend_mag_free": True},
                 "mf": {**_S21A, "unsensed_bend_mag_free": True},
                 "neck3mf": {**_S21A, "lever_pass_bend_sigma_m": 0.003, "lever_pass_iterations": None,
                             "unsensed_bend_mag_free": True},
                 # helper L21: the fixed lag's neck by (N5) with the bend of its bootstrap's (N6) pass (batch: = default)
                 "lagboot": {"lag_neck_from_bootstrap": True},
                 # helper L22: the fixed lag estimates the neck's bend in its own graph (body_lag_neck (L1)–(L4));
                 # "lagstreamNN": the neck levers' bootstrap anchor σ NN mm (L2) instead of 5
                 "lagstream": {"lag_neck_stream": True},
                 "lagstream10": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.01},
                 "lagstream20": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.02},
                 "lagstream50": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.05},
                 # "ovN": the bootstrap's last N s re-streamed (BodyOptions.lag_bootstrap_overlap_s, (L5))
                 "ov1": {"lag_bootstrap_overlap_s": 1.0}, "ov2": {"lag_bootstrap_overlap_s": 2.0},
                 "ls20ov1": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.02, "lag_bootstrap_overlap_s": 1.0},
                 "ls20ov2": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.02, "lag_bootstrap_overlap_s": 2.0},
                 # "bsN": the auto bootstrap's (A1) thresholds × N (BodyOptions.lag_bootstrap_scale, (L6)); "ls20bsN": + lagstream20
                 **{f"bs{n}": {"lag_bootstrap_scale": float(n)} for n in (2, 3, 4)},
                 **{f"ls20bs{n}": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.02, "lag_bootstrap_scale": float(n)}
                    for n in (2, 3, 4)},
                 # "marg": the bootstrap's factors in the smoother, N-pose kept, bRs re-estimated (lag_bootstrap_marginal, (L7))
                 "marg": {"lag_bootstrap_marginal": True},
                 "lsmarg": {"lag_neck_stream": True, "lag_bootstrap_marginal": True},
                 **{f"lsmargbs{n}": {"lag_neck_stream": True, "lag_bootstrap_marginal": True, "lag_bootstrap_scale": float(n)}
                    for n in (2, 3, 4)},
                 # "lsmargsetN" / "ls20setN": the bootstrap extended until bRs moves < 0.N° per second (A2)
                 **{f"lsmargset{n}": {"lag_neck_stream": True, "lag_bootstrap_marginal": True,
                                      "lag_bootstrap_settle_deg": n / 10} for n in (2, 3, 5)},
                 **{f"ls20set{n}": {"lag_neck_stream": True, "lag_neck_anchor_sigma_m": 0.02,
                                    "lag_bootstrap_settle_deg": n / 10} for n in (2, 3, 5)},
                 # "lsmargset3mo": + the bootstrap's (N9) lever offset on the stream's bend with magnetometers (L8)
                 "lsmargset3mo": {"lag_neck_stream": True, "lag_bootstrap_marginal": True, "lag_bootstrap_settle_deg": 0.3,
                                  "lag_neck_mag_offset": True},
                 "lsmargbs3mo": {"lag_neck_stream": True, "lag_bootstrap_marginal": True, "lag_bootstrap_scale": 3.0,
                                 "lag_neck_mag_offset": True}}
# helper B23: "causal" = BodyOptions.lag_init_causal (body_lag_boot.causal_start (C1)); "NAMEc": preset NAME + it
NECK_VARIANTS.update({"causal": {"lag_init_causal": True},
                      **{f"{k}c": {**NECK_VARIANTS[k], "lag_init_causal": True}
                         for k in ("marg", "lsmarg", "lsmargset3", "lsmargset3mo", "lsmargbs3mo")}})


def _label(head: str, use_mag: bool, lag, uns, neck: str) -> str:
    """A solve's label: head (motion, and seed), magnetometer, lag, unsensed σ and --neck variant when not default."""
    return (f"{head} {'mag' if use_mag else 'no-mag'}" + ("" if lag is None else f" lag {lag:g}")
            + ("" if uns is None else f" uns{uns:g}") + ("" if neck == "default" else f" {neck}"))


def run_case(name: str, seed: int, duration: float | None, lower: bool, mags: list[bool],
             lags: list, tie: bool = False, bias_walk: float = 0.0, opts_kw: dict | None = None,
             unsensed: tuple = (None,), necks: tuple = ("default",)) -> list[dict]:
    """Simulate one motion once, solve it with and/or without magnetometers, score; one record per solve
    (opts_kw: extra BodyOptions fields, e.g. hinges and axial_segments; unsensed: values of
    BodyOptions.unsensed_sigma_rad in degrees, None = the default lumped model, one solve each)."""
    from imugraph.body.evaluate import score_against_truth

    skel, session, mask = simulated_session(name, seed, duration, lower, tie=tie, bias_walk=bias_walk)
    out = []
    for use_mag, lag, uns, neck in ((m, g, u, v) for m in mags for g in lags for u in unsensed for v in necks):
        label = _label(f"{name} s{seed}", use_mag, lag, uns, neck)
        kw = dict(opts_kw or {}, **({} if uns is None else {"unsensed_sigma_rad": float(np.deg2rad(uns))}))
        kw.update(NECK_VARIANTS[neck])
        t0 = time.perf_counter()
        try:
            result = _solve(session, use_mag, lag, kw)
        except Exception as exc:              # record a solver failure, go on with the other cases
            print(f"  {label}: failed ({type(exc).__name__}: {str(exc)[:160]})")
            continue
        secs = time.perf_counter() - t0
        scores = score_against_truth(result, session.truth, skel, mask)
        out.append({"label": label, "motion": name, "seed": seed, "use_mag": use_mag, "lag_s": lag, "unsensed_deg": uns,
                    "neck": neck,
                    "realtime_factor": result.info.get("realtime_factor"), "samples": int(session.n),
                    "bootstrap_s": result.info.get("bootstrap", {}).get("bootstrap_s"),
                    "duration_s": float(session.t[-1]), "sensors": len(session.sensors), "seconds": secs,
                    "iterations": [p.get("iterations") for p in result.info.get("passes", [])],
                    "npose": result.info.get("npose"), "scores": scores, "row": summary_row(label, scores, secs),
                    **({"knee_gain": result.info["knee_gain"]} if "knee_gain" in result.info else {})})
        print(f"  {label}: {session.n} samples, {len(session.sensors)} IMUs, {secs:.1f} s, joint max "
              f"{out[-1]['row']['joint_max_deg']:.2f}° ({out[-1]['row']['worst_joint']}), position RMS "
              f"{out[-1]['row']['pos_rms_cm']:.2f} cm", flush=True)
        if lag is not None and _FILTERED and "filtered" in result.info:     # --lag-filtered (helper L22)
            fs = score_against_truth(result.info["filtered"], session.truth, skel, mask)
            out.append(dict(out[-1], label=label + " filtered", neck=neck + " filtered", scores=fs,
                            row=summary_row(label + " filtered", fs, secs)))
    return out


def seed_summary(records: list[dict]) -> list[list]:
    """Rows per (motion, magnetometer, lag) over the seeds: seeds, worst joint RMSE (max over seeds, its seed and
    joint), median of the per-seed worst joint, position RMS (max, median), worst single segment, targets met."""
    groups: dict = {}
    for r in records:
        groups.setdefault((r["motion"], r["use_mag"], r["lag_s"], r.get("unsensed_deg"), r.get("neck", "default")),
                          []).append(r)
    rows = []
    for (motion, mag, lag, uns, neck), rs in groups.items():
        jm = [r["row"]["joint_max_deg"] for r in rs]
        pr = [r["row"]["pos_rms_cm"] for r in rs]
        pw = [r["row"]["pos_worst_cm"] for r in rs]
        w = int(np.argmax(jm))
        ok = max(jm) <= 2.0 and max(pr) <= 2.0
        rows.append([_label(motion, mag, lag, uns, neck), len(rs),
                     max(jm), f"s{rs[w]['seed']} {rs[w]['row']['worst_joint']}", float(np.median(jm)), max(pr),
                     float(np.median(pr)), f"{max(pw):.2f} {rs[int(np.argmax(pw))]['row']['worst_segment']}",
                     "yes" if ok else "NO"])
    return rows


SEED_COLUMNS = ["motion", "seeds", "joint max (°)", "where", "median joint max", "pos RMS max (cm)",
                "median pos RMS", "worst segment (cm)", "≤ 2°/2 cm"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motions", default=",".join(MOTIONS))
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (placements, biases, noise)")
    ap.add_argument("--duration", type=float, default=None, help="BVH seconds to use (default: all)")
    ap.add_argument("--lower", action="store_true", help="7-sensor lower body instead of 17 sensors")
    ap.add_argument("--mag", choices=("both", "off", "on"), default="both")
    ap.add_argument("--tie", action="store_true", help="truth's unsensed segments follow the estimator's ties")
    ap.add_argument("--bias-walk", type=float, default=0.0, metavar="SIGMA",
                    help="gyro bias random walk, rad/s/√s (default 0: constant biases)")
    ap.add_argument("--lag", type=float, default=None, help="also run the fixed-lag smoother with this lag, s")
    ap.add_argument("--hinges", default="", help="'knees' or comma-separated hinge child segments (BodyOptions.hinges)")
    ap.add_argument("--axial", default="", help="'shanks', 'thighs', 'legs' or segments (BodyOptions.axial_segments)")
    ap.add_argument("--unsensed", default="off", help="σ in degrees (comma-separated; 'off': lumped joints) of "
                    "BodyOptions.unsensed_sigma_rad")
    ap.add_argument("--unsensed-prior", choices=("shared", "fixed"), default=None, help="BodyOptions.unsensed_prior")
    ap.add_argument("--unsensed-chains", default="", help="comma-separated distal segments (BodyOptions.unsensed_chains)")
    ap.add_argument("--unsensed-npose-sigma", type=float, default=None, help="unsensed_npose_sigma_rad in degrees")
    ap.add_argument("--unsensed-gain", type=float, default=None, help="BodyOptions.unsensed_sigma_gain (rad per rad)")
    ap.add_argument("--neck", default="default", help="comma-separated of " + ", ".join(NECK_VARIANTS)
                    + " (session 21, imugraph.graphs.body_neck)")
    ap.add_argument("--lag-bootstrap", type=float, default=None, metavar="S",
                    help="the fixed lag's batch bootstrap in s (solve_body_incremental bootstrap_s; default: auto)")
    ap.add_argument("--lag-only", action="store_true", help="with --lag: skip the batch solves (helper L22)")
    ap.add_argument("--lag-iterations", type=int, default=None, help="solve_body_incremental lag_iterations (helper L22)")
    ap.add_argument("--lag-filtered", action="store_true", help="with --lag: also score its filtered (causal) output")
    ap.add_argument("--out", default="body_sim_accuracy.json", help="file name in bench_out/")
    a = ap.parse_args(argv)
    legs = {"thighs": ("RightUpperLeg", "LeftUpperLeg"), "shanks": ("RightLowerLeg", "LeftLowerLeg"),
            "knees": ("RightLowerLeg", "LeftLowerLeg")}
    legs["legs"] = legs["thighs"] + legs["shanks"]
    opts_kw = {k: legs.get(v, tuple(x for x in v.split(",") if x)) for k, v in
               (("hinges", a.hinges), ("axial_segments", a.axial)) if v}
    mags = {"both": [False, True], "off": [False], "on": [True]}[a.mag]
    if a.lag_filtered:
        _FILTERED.append(True)
    if a.lag_iterations is not None:
        _LAG_KW["lag_iterations"] = a.lag_iterations
    if a.lag_bootstrap is not None:
        _LAG_KW["bootstrap_s"] = a.lag_bootstrap
    unsensed = tuple(None if v == "off" else float(v) for v in a.unsensed.split(","))
    if a.unsensed_prior:
        opts_kw["unsensed_prior"] = a.unsensed_prior
    if a.unsensed_gain is not None:
        opts_kw["unsensed_sigma_gain"] = a.unsensed_gain
    if a.unsensed_npose_sigma is not None:
        opts_kw["unsensed_npose_sigma_rad"] = float(np.deg2rad(a.unsensed_npose_sigma))
    if a.unsensed_chains:
        opts_kw["unsensed_chains"] = tuple(x for x in a.unsensed_chains.split(",") if x)
    records = []
    for name in a.motions.split(","):
        if not motion_path(name).exists():
            print(f"  {name}: {motion_path(name)} absent, skipped")
            continue
        for seed in (int(s) for s in a.seeds.split(",")):
            lags = ([] if a.lag_only and a.lag else [None]) + ([a.lag] if a.lag else [])
            records += run_case(name, seed, a.duration, a.lower, mags, lags, a.tie,
                                a.bias_walk, opts_kw, unsensed, tuple(a.neck.split(",")))
    if not records:
        print("no motion data found")
        return 1
    print()
    print_table([r["row"] for r in records], SUMMARY_COLUMNS)
    print()
    summary = seed_summary(records)
    print_table(summary, SEED_COLUMNS)
    joints = sorted({j for r in records for j in r["scores"]["joints"]})
    print()
    print_table([[r["label"]] + [r["scores"]["joints"][j]["all"] if j in r["scores"]["joints"] else "" for j in joints]
                 for r in records], ["joint RMSE (°)"] + joints)
    payload = {"issue": "4a", "noise": NOISE, "rate_hz": 60.0, "lower_body": a.lower, "duration": a.duration,
               "tie_unsensed": a.tie, "gyro_bias_walk": a.bias_walk, "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in opts_kw.items()},
               "unsensed_deg": list(unsensed),
               "targets": {"joint_rmse_deg": 2.0, "position_cm": 2.0}, "peak_memory_mb": peak_memory_mb(),
               "command": "benchmarks/body_sim_accuracy.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "over_seeds": [dict(zip(SEED_COLUMNS, row)) for row in summary],
               "records": [{k: v for k, v in r.items() if k != "row"} for r in records]}
    print(f"\nwrote {write_json(a.out, payload)}; peak memory {peak_memory_mb():.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
