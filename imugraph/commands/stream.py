"""`imugraph stream SESSION`: the session fed sample by sample, in arrival order, to iSAM2 (or a fixed-lag
smoother with --lag), starting from a short batch bootstrap calibration (or --calibration FILE) that is
re-estimated online (held fixed with `--fixed-calibration` when the parser offers it; `--lag-solver` picks
the fixed-lag solver for --lag: chain (default), incremental or batch, `StreamOptions.fixed_lag_solver`;
`--calib-states`, `--disturb` (causal disturbance windows, `StreamOptions.disturb_detect`), `--weak-prior`
(`StreamOptions.calib_weak_prior`) and `--disturb-offsets` (`StreamOptions.disturb_offsets`: each window its own
hard-iron offset, the reported hard iron the majority's) likewise when offered). timing.json's counts include the disturbance windows
found and the keyframes / field samples they flagged (`disturbances`, `disturbed_keyframes`, `disturbed_samples`).

Writes (DESIGN.md): orientation.npz (smoothed, at the end), orientation_filtered.npz (the estimate available
when each sample arrived), calibration.json (the calibration at the end; with StreamOptions.calib_states the streamed D, o,
dip estimated with the orientations, imugraph.graphs.stream_calstate; with the end-of-stream graph of full iSAM2 what
it used: the normal state's streamed θ and each detector window's final Δo_w as a modelled `disturbances` entry, so
`smooth --calibration` reproduces orientation.npz, with StreamOptions.calib_json_end_graph; the majority swap's
hard iron is the last history row's), calibration_history.json (the start calibration and one row per online
refit: t, D, o, dip_deg, std, ...), the figures stream_calibration.png, stream_orientation.png and stream_timing.png
(`write_stream_figures`), timing.json (updates, seconds, p50_ms, p99_ms, plus max_ms, realtime_factor,
the CPU-time figures, the between-keyframe steps' p50/p99/max, bootstrap_seconds, bootstrap_samples, bootstrap_span_s
(the seconds the bootstrap actually used: it grows past --bootstrap-s while they hold too little rotation),
bootstrap_note (the same in words, as printed) and the arrival counters; docs/stream.md).

`--bootstrap-regrow` (helper S23, off by default): streaming starts after a short bootstrap (capped at
--bootstrap-max-s, else at --bootstrap-s) and the bootstrap keeps growing in the background (windows
--bootstrap-regrow-grow apart, `stream_regrow.push_regrow`): each window is calibrated on the rows already arrived; one
that identifies D, o (or, before that, a longer weak one at its weak prior's centre) is replayed by a new smoother that
takes over once that work's CPU time (or --bootstrap-regrow-latency) has passed in stream time, its output turned about
the vertical to continue the heading; after an identified switch growth goes on: a longer window that differs (beyond
3 reported std and 0.5° of field direction, eqs. C1, C2) is switched to, one --bootstrap-regrow-confirm times longer
that agrees ends it. timing.json then has `regrow` (one entry per window: span_s, rows, identified, kind
identified / weak / refused, decision, switched_t: stream time of the switch or null, D, o, cpu_s) and
`regrow_cpu_seconds`; its per-update figures (p50/p99/max, between steps) count the live smoother's updates only,
the replays being background work, while cpu_seconds / cpu_realtime_factor include them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from imugraph.commands import common


def _flag(args: argparse.Namespace, name: str, default: bool) -> bool:
    """A --flag/--no-flag value when the parser offers it and it was given, else the StreamOptions default."""
    value = getattr(args, name, None)
    return default if value is None else bool(value)


def write_stream_figures(out: Path, session, result) -> list[str]:
    """stream_calibration.png (the calibration as it evolved, when calibrated online), stream_orientation.png
    (filtered and smoothed against the session's reference orientation when it has one, else against each other)
    and stream_timing.png (time per update): imugraph.io.stream_figures. Returns the file names written."""
    from imugraph.io.stream_figures import plot_stream_calibration, plot_stream_orientation, plot_stream_timing

    names = []
    if result.calibration_history:
        plot_stream_calibration(out / "stream_calibration.png", result.calibration_history, result.calibration,
                                title=f"Calibration as it was streamed: {session.name}")
        names.append("stream_calibration.png")
    from imugraph.errors import ImugraphError

    title = f"Filtered and smoothed orientation: {session.name}"
    try:
        plot_stream_orientation(out / "stream_orientation.png", result.t, result.filtered, result.smoothed,
                                session.quat, session.movement, title=title,
                                reference_label=common.reference_label(session))
    except ImugraphError:            # a reference that cannot be scored (all NaN, too short): the two estimates
        plot_stream_orientation(out / "stream_orientation.png", result.t, result.filtered, result.smoothed,
                                title=title)
    names.append("stream_orientation.png")
    if result.update_ms is not None and result.update_ms.size:
        plot_stream_timing(out / "stream_timing.png", result.update_t, result.update_ms, result.update_cpu_ms,
                           title=f"Time per keyframe update: {session.name}")
        names.append("stream_timing.png")
    return names


# StreamStats counters → words of the arrival line (those not listed print with their field name)
ARRIVAL_WORDS = {"duplicates": "duplicate", "late_inserted": "late, inserted", "late_dropped": "late, dropped",
                 "invalid": "invalid", "gaps": "gaps", "missing": "missing", "mag_dropped": "magnetometer dropped",
                 "failed_updates": "failed updates", "marginal_steps": "marginal steps",
                 "calib_refits": "calibration refits", "disturbances": "disturbance windows",
                 "disturbed_keyframes": "disturbed keyframes", "disturbed_samples": "disturbed samples"}


def arrival_line(counts: dict) -> str:
    """The non-zero arrival counters as one readable line ("  arrival: 3 duplicate, 2 gaps"), or "" when none
    (accepted and mag_samples are in the summary line already)."""
    parts = [f"{v} {ARRIVAL_WORDS.get(k, k)}" for k, v in counts.items()
             if v and k not in ("accepted", "mag_samples")]
    return f"  arrival: {', '.join(parts)}" if parts else ""


def ignored_flags(args: argparse.Namespace) -> list[str]:
    """Flags given on the command line that this combination ignores (each a one-line reason): a warning on
    stderr, the run unchanged (StreamOptions applies them only where stated)."""
    given = lambda name: getattr(args, name, None) is True          # noqa: E731 — explicitly --name
    lag = getattr(args, "lag", None) is not None
    out = []
    if given("calib_json_end_graph") and lag:
        out.append("--calib-json-end-graph has no effect with --lag (the end-of-stream graph is full iSAM2's)")
    if given("disturb_offsets") and (getattr(args, "calib_states", None) is False or getattr(args, "disturb", None) is False):
        out.append("--disturb-offsets has no effect with --no-calib-states or --no-disturb (it needs both)")
    if given("calib_states") and getattr(args, "fixed_calibration", False):
        out.append("--calib-states has no effect with --fixed-calibration (no online calibration)")
    if getattr(args, "bootstrap_regrow", False) and getattr(args, "calibration", None):
        out.append("--bootstrap-regrow has no effect with --calibration (no bootstrap)")
    if not lag and getattr(args, "lag_solver", "chain") not in (None, "chain"):
        out.append(f"--lag-solver {args.lag_solver} has no effect without --lag")
    return out


def regrow_keywords(args: argparse.Namespace) -> dict:
    """--bootstrap-regrow (helper S23) as stream_session keywords: the bootstrap capped at --bootstrap-max-s (else at
    --bootstrap-s: no growth before streaming), then grown while streaming (bootstrap_regrow "weak": each longer weak
    window too, at its weak prior's centre), the heading kept across a switch (regrow_align), windows
    --bootstrap-regrow-grow apart, growth on until a window --bootstrap-regrow-confirm times longer agrees
    (regrow_confirm; stream_regrow eqs. C1, C2). {} without the flag (the default: the bootstrap grows first)."""
    if not getattr(args, "bootstrap_regrow", False):
        return {}
    cap = getattr(args, "bootstrap_max_s", None)
    return {"bootstrap_max_s": args.bootstrap_s if cap is None else cap, "bootstrap_regrow": "weak",
            "bootstrap_weak_centre": True, "regrow_align": True, "regrow_grow": args.bootstrap_regrow_grow,
            "regrow_confirm": args.bootstrap_regrow_confirm, "regrow_latency_s": args.bootstrap_regrow_latency}


def run_stream(args: argparse.Namespace) -> int:
    """stream SESSION [--out DIR] [--lag S] [--bootstrap-s S] [--calibration FILE] [--keyframe-hz HZ].

    Flags this combination ignores are named in one warning line each on stderr (`ignored_flags`)."""
    progress = common.Progress(args.quiet)
    for reason in ignored_flags(args):
        print(f"imugraph: warning: {reason}; ignored", file=sys.stderr, flush=True)
    path, session, cal = common.load_with_calibration(args, progress)      # a bad --calibration fails first
    with common.output_folder(args.out, Path(path).stem) as out:     # no empty folder left by a failed run
        return _stream_into(out, args, session, cal, progress)


def _stream_into(out: Path, args: argparse.Namespace, session, cal, progress: common.Progress) -> int:
    """The stream and its outputs in `out` (run_stream's body once the session is read)."""
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import stream_session
    from imugraph.io.writers import atomic_write_text, json_ready, write_orientation_npz

    lag_solver = getattr(args, "lag_solver", None) or StreamOptions.fixed_lag_solver   # `--lag-solver` if offered
    # --calib-states, --disturb, --weak-prior, --disturb-offsets when the parser offers them (cli.py; StreamOptions' defaults otherwise)
    options = StreamOptions(keyframe_hz=args.keyframe_hz, lag_s=args.lag, fixed_lag_solver=lag_solver,
                            online_calibration=not getattr(args, "fixed_calibration", False),
                            calib_states=_flag(args, "calib_states", StreamOptions.calib_states),
                            disturb_detect=_flag(args, "disturb", StreamOptions.disturb_detect),
                            calib_weak_prior=_flag(args, "weak_prior", StreamOptions.calib_weak_prior),
                            disturb_offsets=_flag(args, "disturb_offsets", StreamOptions.disturb_offsets),
                            calib_json_end_graph=_flag(args, "calib_json_end_graph", StreamOptions.calib_json_end_graph))
    with progress.library_output():
        # --bootstrap-max-s when the parser offers it (the bootstrap's growth capped; None: grows to the session's end)
        kw = {"bootstrap_max_s": getattr(args, "bootstrap_max_s", None), **regrow_keywords(args)}
        result = stream_session(session, cal, options, bootstrap_s=args.bootstrap_s, say=progress.say, **kw)
    write_orientation_npz(out / "orientation.npz", result.t, result.smoothed)
    write_orientation_npz(out / "orientation_filtered.npz", result.t, result.filtered)
    common.write_calibration(out, result.calibration, progress)
    history = {"start": result.start_calibration.to_dict(), "calibration_history": result.calibration_history}
    atomic_write_text(out / "calibration_history.json", json.dumps(json_ready(history), indent=2))
    timing = dict(result.timing, bootstrap_samples=result.bootstrap_samples, counts=result.counts,
                  solver="isam2" if args.lag is None else f"fixed_lag {args.lag:g} s ({lag_solver})")
    atomic_write_text(out / "timing.json", json.dumps(timing, indent=2))
    progress.say(f"wrote {out}/orientation.npz, orientation_filtered.npz, "      # calibration.json: said above
                 "calibration_history.json, timing.json")
    progress.say(f"drawing figures: {', '.join(write_stream_figures(out, session, result))}")
    tm = result.timing
    print(f"streamed {session.name}: {session.n} samples, {tm['updates']} updates, "
          f"{tm['realtime_factor']:.1f}× real time, update p50 {tm['p50_ms']:.2f} ms, p99 {tm['p99_ms']:.2f} ms → {out}")
    reference = common.reference_label(session)          # "truth", or a device's own estimate (quat_source)
    for label, quat in (("filtered", result.filtered), ("smoothed", result.smoothed)):
        rms = common.orientation_score(session, quat)
        if rms is not None:
            print(f"  {label} orientation error vs {reference}: {rms:.2f}° RMS")
    line = arrival_line(result.counts)
    if line:
        print(line)
    return 0
