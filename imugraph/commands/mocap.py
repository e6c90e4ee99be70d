"""`imugraph mocap SESSION`: body motion from several IMUs on one body (the factor graph of imugraph.graphs.body).

SESSION: a body-session folder (session.json), a gaittoolbox Xsens MTw ``rawimu`` folder, an .mvnx file, a folder
of x-IMU3 export folders, or the qmt full-body .mat
(`imugraph.io.body_session.read_body_session`); a relative path that does not exist is looked up in the data
directory (--data-dir, $IMUGRAPH_DATA, ../shared/data).

Writes in --out DIR (default imugraph_out/<session name>):
    mocap.npz          t (T), segments (S names), quat (T×S×4, segment→world, w,x,y,z), pos (T×S×3, m) — DESIGN.md
    joint_angles.csv   t,<Joint>_flexion,<Joint>_abduction,<Joint>_rotation,… (degrees, imugraph.body.angles)
    motion.bvh         the skeleton and motion as BVH (rest pose = neutral N-pose, metres)
    joint_angles.png   joint angles over time (dashed: the session's truth when it has one)
    stick_figures.png  skeleton snapshots, sagittal and frontal
    mocap_info.json    solver (batch / fixed-lag), options, timing, estimated sensor placements, and the
                       scores against the truth when the session is simulated
  with --lag also:
    mocap_filtered.npz the estimate available right after each keyframe's update (causal), same keys as mocap.npz
    timing.json        updates, seconds, p50_ms, p99_ms, max_ms, realtime_factor, bootstrap, bootstrap_note

Options: --lag S runs the fixed-lag incremental solver keeping S seconds instead of batch LM; --mag uses the
magnetometers (default off: indoor fields near the body are rarely homogeneous); --hinges LIST treats joints
as hinges (comma-separated: knees, elbows, or joint names RightKnee, LeftElbow, … or child segment names);
--skeleton SPEC replaces the session's skeleton (height:H, or bvh:PATH: the OFFSETs of a BVH hierarchy);
--npose T0,T1 gives the static N-pose window instead of detecting it; --init motion starts every sensor at the
heading about the vertical its joint accelerations imply (imugraph.body.placement_motion) instead of its nominal site
(a suit strapped on another way, e.g. the qmt full-body file: converged instead of stopping at the iteration limit);
--init auto (the default since session 22) does that only for the sensors more than 45° from their nominal site;
--init nominal is the start before session 22. --npose-search anywhere (helper B23, opt-in): a session with no rest at
its start is solved from the quietest common rest of all sensors (≥ 1 s) anywhere, said on stderr; with none, one
error line asking for --npose T0,T1 (default "start": the first samples are assumed to be the N-pose, as before).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np

from imugraph.commands import common
from imugraph.errors import SessionError

HINGE_GROUPS = {"knees": ("RightKnee", "LeftKnee"), "elbows": ("RightElbow", "LeftElbow")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The mocap subcommand's arguments (cli.py calls this; the lead wires it)."""
    p.add_argument("session", metavar="SESSION",
                   help="body session: folder with session.json (sensor NPZ without magnetometer accepted: mocap "
                        "runs without magnetometers by default), gaittoolbox rawimu folder, folder of x-IMU3 export "
                        "folders (one per segment), qmt full-body .mat, or .mvnx file")
    p.add_argument("--out", metavar="DIR", default=None, help="output folder (default: imugraph_out/<session name>)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--data-dir", metavar="DIR", default=None,
                   help="where to look for SESSION when it does not exist as given "
                        "(default: $IMUGRAPH_DATA, else ../shared/data)")
    p.add_argument("--lag", type=float, default=None, metavar="S",
                   help="fixed-lag incremental smoother keeping S seconds (default: batch over the whole session)")
    p.add_argument("--mag", action=argparse.BooleanOptionalAction, default=False,
                   help="use the magnetometers (per-sensor field direction from the N-pose; default: --no-mag)")
    p.add_argument("--hinges", metavar="LIST", default="",
                   help="joints constrained to hinges about the lateral axis: knees, elbows, or joint names "
                        "(RightKnee, LeftElbow, ...), comma-separated")
    p.add_argument("--npose", metavar="T0,T1", default=None,
                   help="the static N-pose window in the session's own time, s (default: detected, the common rest "
                        "of all sensors at the start; e.g. 40,44 for qmt_full_body, whose upper-arm sensors read "
                        "0.04 rad/s at rest)")
    p.add_argument("--npose-search", choices=("start", "anywhere"), default="start",
                   help="without --npose: start (default: the common rest at the start; if there is none the first "
                        "samples are assumed to be it) or anywhere (helper B23: no rest at the start → the quietest "
                        "common rest of ≥ 1 s anywhere, said on stderr, solved from there on; none → a one-line error "
                        "asking for --npose)")
    p.add_argument("--init", choices=("nominal", "motion", "auto"), default="auto",
                   help="sensor-on-segment start: auto (default: the motion start only for sensors > 45° from their "
                        "nominal site), nominal (the standard sites; before session 22) or motion (every sensor's "
                        "heading about the vertical from the joint accelerations after the N-pose)")
    p.add_argument("--skeleton", metavar="SPEC", default="nominal",
                   help="segment lengths and joint positions: nominal (the session's own), height:H (Winter's "
                        "proportions for body height H m), or bvh:PATH (the HIERARCHY OFFSETs of a BVH file, looked "
                        "up in --data-dir like SESSION, e.g. "
                        "the subject's dimensions in an Xsens MVN export; its motion is not used)")


def hinge_segments(spec: str, skel, ignored: list | None = None) -> tuple:
    """Child segment names of the hinge joints in `spec` (module docstring).

    ignored: when a list, a group name (knees, elbows) with no joint between sensed segments in this skeleton
    (elbows on a lower body) is appended to it, so that the command can say it was ignored.

    Raises:
        SessionError: an unknown name, or a joint whose segments are not both sensed in the skeleton.
    """
    from imugraph.body.angles import JOINTS

    out = []
    for item in (s.strip() for s in (spec or "").split(",")):
        if not item:
            continue
        names = HINGE_GROUPS.get(item.lower(), (item,))
        for name in names:
            if name in JOINTS:
                child = JOINTS[name][1]
            elif name in skel.names:
                child = name
            else:
                raise SessionError("--hinges", item, "an unknown joint", "knees, elbows, a joint name "
                                   f"({', '.join(j for j in JOINTS if 'Knee' in j or 'Elbow' in j)}) or a segment")
            if child not in skel.sensed or skel.parents[skel.index(child)] < 0:
                if item.lower() in HINGE_GROUPS:
                    if ignored is not None and f"{item} ({name})" not in ignored:
                        ignored.append(f"{item} ({name})")
                    continue                       # e.g. elbows on a lower-body skeleton: nothing to constrain
                raise SessionError("--hinges", item, f"segment {child} not sensed in this skeleton",
                                   f"a joint between sensed segments of {list(skel.sensed)}")
            if child not in out:
                out.append(child)
    return tuple(out)


def npose_window(spec) -> tuple | None:
    """--npose "T0,T1" → (T0, T1) s (BodyOptions.npose); None → None (detected).

    Raises:
        SessionError: not two numbers with T0 < T1.
    """
    if spec is None or str(spec).strip() == "":
        return None
    try:
        t0, t1 = (float(x) for x in str(spec).split(","))
    except ValueError:
        raise SessionError("--npose", "T0,T1", repr(spec), "two times in s, e.g. 40,44") from None
    if not t0 < t1:
        raise SessionError("--npose", "T0,T1", repr(spec), "T0 < T1")
    return (t0, t1)


def apply_skeleton(session, spec: str, data_dir: str | None = None):
    """`session` with its skeleton replaced by the one `spec` names (`imugraph.body.skeleton.skeleton_from_spec`,
    restricted to the session's segments, the session's sensed set kept); 'nominal' returns it unchanged.

    Raises:
        SessionError: a bad spec, or a BVH without joints for the session's segments (naming the file).
    """
    import dataclasses

    from imugraph.body.skeleton import skeleton_from_spec

    skel = session.skeleton
    new = skeleton_from_spec(spec, skel.names, data_dir)     # bvh:PATH looked up like SESSION
    if new is None:
        return session
    new = dataclasses.replace(new, sensed=tuple(s for s in skel.sensed))
    meta = dict(session.meta, skeleton=f"--skeleton {spec}")
    return dataclasses.replace(session, skeleton=new, meta=meta)


def write_mocap_npz(path: Path, t: np.ndarray, names, quat: np.ndarray, pos: np.ndarray) -> Path:
    """mocap.npz (DESIGN.md): t (T), segments (S), quat (T, S, 4), pos (T, S, 3); atomic."""
    from imugraph.io.writers import atomic_write_bytes

    buf = io.BytesIO()
    np.savez(buf, t=np.asarray(t, float), segments=np.array(list(names), dtype=str),
             quat=np.asarray(quat, float), pos=np.asarray(pos, float))
    return atomic_write_bytes(path, buf.getvalue())


def start_at_npose(session, opts) -> tuple:
    """--npose-search anywhere (helper B23): (session, npose window or None). A rest at the start: unchanged (None:
    detected as before). Otherwise the quietest common rest anywhere (imugraph.graphs.body_init.find_npose): the
    session from its first sample on (the estimator assumes its N-pose at the start of the data) with that window,
    said in one line on stderr and kept in session.meta["npose_search"] (mocap_info.json).

    Raises:
        SessionError: no common rest of ≥ 1 s anywhere (one line naming the session, asking for --npose T0,T1).
    """
    import dataclasses

    from imugraph.graphs.body_init import find_npose

    _, method, info = find_npose(session, opts)
    if method != "found":
        return dataclasses.replace(session, meta=dict(session.meta, npose_search=info)), None
    t0 = float(session.t[0])
    cut = session.slice(info["start_row"], session.n)
    print(f"imugraph: note: {session.name}: no rest at the start; N-pose = the quietest common rest of all sensors, "
          f"{info['t0'] - t0:.2f}–{info['t1'] - t0:.2f} s; solved from {info['t0'] - t0:.2f} s on (the "
          f"{info['t0'] - t0:.1f} s before it are not in the output)", file=sys.stderr, flush=True)
    return dataclasses.replace(cut, meta=dict(cut.meta, npose_search=info)), (info["t0"], info["t1"])


def check_npose_in_session(session, npose: tuple, min_after_s: float = 2.0) -> None:
    """--npose T0,T1 against the session: inside its time span, and followed by at least `min_after_s` of data (the
    estimator needs motion after its N-pose). A window that is not at rest is said on stderr (the user's call).

    Raises:
        SessionError: the window outside the session, or with too little data after it (one line, found and expected).
    """
    from imugraph.calibration.rest import detect_rest

    t = np.asarray(session.t, float)
    t0, t1 = npose
    if t0 < t[0] - 1e-9 or t1 > t[-1] - min_after_s:
        raise SessionError(session.source, "--npose", f"{t0:g},{t1:g} s",
                           f"a window inside the session's {t[0]:g}–{t[-1]:g} s leaving ≥ {min_after_s:g} s after it")
    sel = (t >= t0) & (t <= t1)
    still = min(float(np.mean(detect_rest(s)[sel])) for s in session.sensors.values())
    if still < 0.5:
        print(f"imugraph: warning: {session.name}: --npose {t0:g},{t1:g}: some sensor rests in only {100 * still:.0f} % "
              "of the window; the N-pose is expected to be a standing rest", file=sys.stderr, flush=True)


def warn_assumed_npose(session, opts) -> None:
    """Default --npose-search start: when no common rest of all sensors starts the session, the solver assumes its
    first samples to be the N-pose (body_model.npose_samples "assumed") — say so in one line (U23 defect 2), since a
    session that starts moving solves into garbage that way."""
    from imugraph.graphs.body_model import npose_samples

    _, method = npose_samples(session, opts)
    if method == "assumed":
        print(f"imugraph: warning: {session.name}: no common rest of all sensors at the start; its first samples are "
              "assumed to be the N-pose and the result may be wrong — give the N-pose with --npose T0,T1 or let "
              "--npose-search anywhere find a rest", file=sys.stderr, flush=True)


def _solve(session, opts, lag, progress):
    """Batch LM, or the fixed-lag smoother (imugraph.graphs.body_incremental) when --lag is given."""
    if lag is None:
        from imugraph.graphs.body import solve_body_batch
        progress.say(f"batch solve: {len(session.sensors)} sensors, {session.n} samples")
        return solve_body_batch(session, opts), "batch"
    if not lag > 0:
        raise SessionError("--lag", "S", str(lag), "a lag > 0 s")
    try:
        from imugraph.graphs.body_incremental import solve_body_incremental
    except ImportError:
        raise SessionError("--lag", "solver", "no incremental body solver in this build",
                           "imugraph.graphs.body_incremental (omit --lag for the batch solver)") from None
    progress.say(f"fixed-lag solve (lag {lag:g} s): {len(session.sensors)} sensors, {session.n} samples")
    return solve_body_incremental(session, opts, lag_s=lag), f"fixed_lag {lag:g} s"


def timing_summary(info: dict, duration_s: float) -> dict:
    """timing.json of an incremental run: updates, seconds, p50_ms, p99_ms, max_ms, realtime_factor (the
    solver's own figure when it reports one: streamed duration over update time, a batch bootstrap excluded),
    realtime_factor_with_bootstrap (the whole duration over update time plus the bootstrap's solve time; equal to
    the duration over update time without a bootstrap), and the bootstrap's details."""
    u = np.asarray(info.get("update_s", []), float)
    note = bootstrap_note(info.get("bootstrap"), duration_s)
    if u.size == 0:
        return {"updates": 0, "bootstrap": info.get("bootstrap"), "bootstrap_note": note}
    rtf = info.get("realtime_factor")
    return {"bootstrap_note": note, "updates": int(u.size), "seconds": float(u.sum()), "p50_ms": float(1e3 * np.percentile(u, 50)),
            "p99_ms": float(1e3 * np.percentile(u, 99)), "max_ms": float(1e3 * u.max()),
            "realtime_factor": float(rtf) if rtf is not None else float(duration_s / max(u.sum(), 1e-12)),
            "realtime_factor_with_bootstrap": float(duration_s / max(u.sum() + _bootstrap_s(info), 1e-12)),
            "failed_updates": int(info.get("failed_updates", 0)), "bootstrap": info.get("bootstrap")}


def bootstrap_note(boot, duration_s: float) -> str | None:
    """The fixed lag's batch bootstrap in words (U23 defect 10, as `stream`'s bootstrap_note): how many of the session's
    seconds it solved as one batch; when it took (nearly) all of them, the "incremental" output is a batch solve."""
    if not isinstance(boot, dict) or "span_s" not in boot:
        return None
    span = float(boot["span_s"])
    note = f"the bootstrap solved the first {span:.1f} s of {duration_s:.1f} s as one batch"
    if span >= 0.9 * duration_s:
        note += (" — nearly the whole session: it holds too little motion for the sensor placements sooner, so the "
                 "output is a batch solve, not a stream")
    return note


def _bootstrap_s(info: dict) -> float:
    """Solve time of the incremental solver's batch bootstrap (info["bootstrap"]["seconds"]), 0 without one."""
    boot = info.get("bootstrap")
    return float(boot.get("seconds", 0.0)) if isinstance(boot, dict) else 0.0


def run_mocap(args: argparse.Namespace) -> int:
    """mocap SESSION [--out DIR] [--lag S] [--mag|--no-mag] [--hinges LIST] [--skeleton SPEC] [--data-dir DIR]
    [--quiet]."""
    from imugraph.graphs.body_model import BodyOptions
    from imugraph.io.body_session import read_body_session

    progress = common.Progress(args.quiet)
    path = common.resolve_session_path(args.session, args.data_dir)
    progress.say(f"reading {path}")
    session = read_body_session(path)
    skel = session.skeleton
    if skel is None:
        raise SessionError(str(path), "skeleton", "none", "a body session with a skeleton")
    session = apply_skeleton(session, getattr(args, "skeleton", "nominal"), args.data_dir)
    no_mag = session.meta.get("no_mag") or [n for n, s in session.sensors.items() if np.isnan(s.mag).all()]
    if args.mag and no_mag:             # 6-axis sensors: fine without magnetometers (the default), not with --mag
        raise SessionError(str(path), "mag", f"no magnetometer samples for {no_mag}", "magnetometer samples in "
                           "every sensor file for --mag (omit --mag: mocap runs without magnetometers by default)")
    skel = session.skeleton
    progress.say(f"{len(session.sensors)} sensors on {len(skel.names)} segments, {session.n} samples, "
                 f"{session.t[-1] - session.t[0]:.1f} s at {session.rate:.1f} Hz")
    ignored: list = []
    hinges = hinge_segments(args.hinges, skel, ignored)
    if ignored:        # a group with nothing to constrain here: said, not silently dropped
        print(f"imugraph: warning: --hinges {', '.join(ignored)}: no such joint between sensed segments of this "
              "skeleton; ignored", file=sys.stderr, flush=True)
    npose = npose_window(getattr(args, "npose", None))
    if npose is not None:
        check_npose_in_session(session, npose)
    elif getattr(args, "npose_search", "start") == "anywhere":
        session, npose = start_at_npose(session, BodyOptions(use_mag=bool(args.mag)))
    else:
        warn_assumed_npose(session, BodyOptions(use_mag=bool(args.mag)))
    opts = BodyOptions(use_mag=bool(args.mag), hinges=hinges, npose=npose, init=getattr(args, "init", "nominal"))
    with common.output_folder(args.out, session.name) as out:     # no empty folder left by a failed run
        return _mocap_into(out, args, path, session, opts, hinges, progress)


def _mocap_into(out: Path, args: argparse.Namespace, path: Path, session, opts, hinges: tuple,
                progress: common.Progress) -> int:
    """run_mocap's body once the session and options are set: solve, write the outputs into `out`, print."""
    from imugraph.body.angles import joint_angles, write_joint_angles_csv
    from imugraph.io.body_figures import plot_joint_angles, plot_stick_figures
    from imugraph.io.bvh import write_bvh
    from imugraph.io.writers import atomic_write_text, json_ready

    skel = session.skeleton
    with progress.library_output():
        result, solver = _solve(session, opts, args.lag, progress)
    written = [write_mocap_npz(out / "mocap.npz", result.t, result.names, result.n_quat, result.n_pos)]
    angles = joint_angles(skel, result.n_quat)
    written.append(write_joint_angles_csv(out / "joint_angles.csv", result.t, angles))
    written.append(write_bvh(out / "motion.bvh", skel, result.t, result.n_quat, result.n_pos[:, 0]))
    timing = {}
    if args.lag is not None:
        timing = timing_summary(result.info, float(session.t[-1] - session.t[0]))
        written.append(atomic_write_text(out / "timing.json", json.dumps(json_ready(timing), indent=1) + "\n"))
        filt = result.info.get("filtered")
        if filt is not None:
            written.append(write_mocap_npz(out / "mocap_filtered.npz", filt.t, filt.names, filt.n_quat, filt.n_pos))
    scores, reference = None, None
    if session.truth is not None and "n_quat" in session.truth:
        from imugraph.body.evaluate import score_against_truth

        scores = score_against_truth(result, session.truth, skel)
        tn = list(session.truth["names"])
        q_ref = np.asarray(session.truth["n_quat"])[:, [tn.index(n) for n in result.names]]
        reference = joint_angles(skel, q_ref)
    progress.say("drawing figures")
    plot_joint_angles(out / "joint_angles.png", result.t, angles, reference, title=f"Joint angles: {session.name}",
                      ref_label="truth")
    plot_stick_figures(out / "stick_figures.png", skel, result.t, result.n_quat, result.n_pos,
                       title=f"Stick figures: {session.name}")
    written += [out / "joint_angles.png", out / "stick_figures.png"]
    info = {"session": str(path), "name": session.name, "solver": solver, "use_mag": bool(args.mag), "init": opts.init,
            "npose_window": list(opts.npose) if opts.npose is not None else None,
            **({"npose_search": session.meta["npose_search"]} if "npose_search" in session.meta else {}),
            "hinges": list(hinges), "skeleton": session.meta.get("skeleton", "session's own"),
            "samples": int(session.n), "segments": list(result.names),
            "placements": result.placements, "info": {k: v for k, v in result.info.items()
                                                      if k in ("build_s", "solve_s", "passes", "keyframes", "npose",
                                                               "factors", "timing", "biases", "joint_names",
                                                               "init_motion")},
            "timing": timing, "scores": scores}
    written.append(atomic_write_text(out / "mocap_info.json", json.dumps(json_ready(info), indent=1) + "\n"))
    progress.say("wrote " + ", ".join(p.name for p in written))
    secs = result.info.get("solve_s", result.info.get("total_s"))
    print(f"mocap {session.name}: {session.n} samples, {len(result.names)} segments, {solver}"
          + (f", solved in {secs:.1f} s" if isinstance(secs, (int, float)) else "") + f" → {out}")
    if timing.get("updates"):
        boot_s = _bootstrap_s(timing)            # timing["bootstrap"] is the solver's info["bootstrap"]
        rtf = (f"{timing['realtime_factor']:.1f}× real time after a {boot_s:.1f} s bootstrap solve "
               f"({timing['realtime_factor_with_bootstrap']:.1f}× including it)" if boot_s
               else f"{timing['realtime_factor']:.1f}× real time")
        print(f"  {timing['updates']} updates, {rtf}, "
              f"update p50 {timing['p50_ms']:.1f} ms, p99 {timing['p99_ms']:.1f} ms")
    if timing.get("bootstrap_note"):
        print(f"  {timing['bootstrap_note']}")
    if scores is not None:
        worst = max(scores["joints"], key=lambda j: scores["joints"][j]["all"])
        print(f"  vs truth: joint-angle RMSE max {scores['joint_rmse_max_deg']:.2f}° ({worst}), "
              f"relative position RMS {100 * scores['position']['rms_m']:.2f} cm")
    return 0
