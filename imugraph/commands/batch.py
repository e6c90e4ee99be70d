"""`imugraph batch SESSIONS… --out DIR [--overwrite] [--scheduler ADDRESS] [--workers N]`: many sessions on Dask.

Each session is calibrated and smoothed on a worker (`imugraph.batch.run_one`), into DIR/<name>/ with the files
of `imugraph calibrate`; <name> is the stem, or the shortest path suffix that tells sessions with the same stem
apart (a/s.npz, b/s.npz → a-s, b-s: `imugraph.batch.path_names`, the same whatever the order of the sessions).
A progress bar and one line per failed session go to stderr; the summary table (with each session's folder) goes
to stdout and to DIR/summary.json + DIR/summary.csv (written atomically).

--out (U23 defect 9): a new or empty DIR. A DIR holding anything is refused at once (one line, exit 2): an earlier
run's session folders would stay beside this run's, unlisted in its summary. --overwrite writes over it; the
session folders the earlier run's summary.json lists that hold no result of this run lose their calibrate files
and are removed when nothing else is in them (what stays is said). A session given twice is computed once (a note
says so; summary.json "repeated": {path: times given}).

Exit status: 0 every session ok; 1 at least one session failed (the others still ran and are written);
2 the batch could not run (bad arguments, --out not writable or holding an earlier run without --overwrite,
scheduler not answering, local cluster not starting; an --out created by this run is removed again);
130 Ctrl-C: the unfinished sessions cancelled, the cluster closed, DIR/summary.json (+ .csv) written
for the sessions that had finished ("interrupted": true), one line "imugraph: interrupted (…)" on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

from imugraph.commands import common
from imugraph.errors import SessionError

EXIT_SOME_FAILED = 1
EXIT_INTERRUPTED = 130     # as imugraph.cli: Ctrl-C (after summary.json of the finished sessions is written)


def run_batch_command(args: argparse.Namespace) -> int:
    """batch SESSIONS… --out DIR [--overwrite] [--scheduler ADDRESS] [--workers N] [--keyframe-hz HZ] [--allow-weak]
    [--gyro-scale | --no-gyro-scale] [--data-dir DIR] [--quiet].

    Returns:
        0 when every session succeeded, 1 when any failed (errors that stop the whole batch are raised
        as ImugraphError and reported by `imugraph.cli.main` with exit status 2).
    """
    from imugraph.batch import (BatchInterrupted, distinct_sessions, local_workers, run_batch, summary_table,
                                write_summary)
    from imugraph.commands.calibrate import CalibrateOptions

    out = Path(args.out).expanduser()
    earlier = check_out(out, getattr(args, "overwrite", False))       # before any cluster starts: exit 2 at once
    paths = [common.resolve_session_path(s, args.data_dir, strict=False) for s in args.sessions]
    files, repeated = distinct_sessions(paths)
    options = CalibrateOptions(args.keyframe_hz, args.allow_weak, getattr(args, "gyro_scale", None))
    say = common.Progress(args.quiet)
    if args.scheduler and args.workers and not args.quiet:
        print("imugraph: note: --workers applies to the local cluster only; ignored with --scheduler",
              file=sys.stderr)
    for path, count in repeated.items():
        if not args.quiet:
            print(f"imugraph: note: {path} given {count} times: computed once", file=sys.stderr)
    n_local = local_workers(args.workers, len(files))
    where = f"the scheduler at {args.scheduler}" if args.scheduler else \
        f"a local cluster of {plural(n_local, 'worker process', 'worker processes')}"
    say.say(f"{plural(len(files), 'session', 'sessions')} on {where} → {args.out}")
    start = time.perf_counter()
    meta = {"scheduler": args.scheduler, "workers": args.workers, "options": asdict(options)}
    if repeated:
        meta["repeated"] = repeated
    try:
        rows = run_batch(files, args.out, scheduler=args.scheduler, workers=args.workers, options=options,
                         progress=not args.quiet)
    except BatchInterrupted as stop:     # Ctrl-C: tasks cancelled, cluster closed; the finished sessions summarised
        meta.update(wall_s=time.perf_counter() - start, interrupted=True, sessions_requested=stop.total)
        _replace_earlier(out, earlier, ok_folders(stop.rows), meta, args.quiet)
        js, _ = write_summary(out, stop.rows, meta)
        print(f"imugraph: interrupted ({len(stop.rows)} of {stop.total} sessions finished; summary in {js})",
              file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    wall = time.perf_counter() - start
    meta = {"wall_s": wall, **meta}
    _replace_earlier(out, earlier, ok_folders(rows), meta, args.quiet)
    js, csv_path = write_summary(out, rows, meta)
    print(summary_table(rows))
    print(f"wall time {wall:.1f} s; summary in {js} and {csv_path}")
    return 0 if all(r["status"] == "ok" for r in rows) else EXIT_SOME_FAILED


def plural(n: int, one: str, many: str) -> str:
    """'1 session', '2 sessions'."""
    return f"{n} {one if n == 1 else many}"


def check_out(out: Path, overwrite: bool) -> Optional[list[str]]:
    """Refuse an --out that holds anything unless --overwrite (U23 defect 9: a second run wrote over the first one's
    folders and left the rest unlisted).

    Returns:
        None for a new or empty folder; with --overwrite the session folders the earlier run's summary.json lists
        (names under `out`; [] when it has none).

    Raises:
        SessionError: field 'out', the folder holds entries and --overwrite was not given.
    """
    if not out.is_dir():
        return None                  # new (created by run_batch), or not a folder: run_batch's own check says so
    entries = sorted(p.name for p in out.iterdir())
    if not entries:
        return None
    if not overwrite:
        what = "an earlier batch run's summary.json and " if "summary.json" in entries else ""
        raise SessionError(str(out), "out", f"a folder holding {what}{plural(len(entries), 'entry', 'entries')} "
                           f"({', '.join(entries[:3])}{', …' if len(entries) > 3 else ''})",
                           "a new or empty folder, or --overwrite to replace the earlier run's results")
    return _earlier_folders(out)


def _earlier_folders(out: Path) -> list[str]:
    """Names of the session folders directly under `out` that its summary.json lists ([] without a readable one)."""
    try:
        doc = json.loads((out / "summary.json").read_text())
        rows = doc["sessions"] if isinstance(doc, dict) else []
        names = [Path(r["out"]).name for r in rows if isinstance(r, dict) and r.get("out")]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    return [n for n in dict.fromkeys(names) if n and (out / n).is_dir()]


def ok_folders(rows: list) -> set[str]:
    """Folder names this run wrote a result into (its sessions with status ok)."""
    return {Path(r["out"]).name for r in rows if r.get("out") and r.get("status") == "ok"}


def _replace_earlier(out: Path, earlier: Optional[list[str]], written: set[str], meta: dict, quiet: bool) -> None:
    """--overwrite: the earlier run's session folders that hold no result of this run (not among its sessions, failed
    or, after Ctrl-C, unfinished) lose their calibrate files and are removed when nothing else is left in them; what
    stays is said and listed in meta["overwrite"]."""
    from imugraph.batch import SESSION_FILES

    if earlier is None:
        return
    removed, kept = [], []
    for name in earlier:
        if name in written:
            continue
        folder = out / name
        for f in SESSION_FILES:
            with contextlib.suppress(FileNotFoundError):
                (folder / f).unlink()
        try:
            folder.rmdir()
            removed.append(name)
        except OSError:
            kept.append(name)
    meta["overwrite"] = {"removed": removed, "kept": kept}
    if not quiet and (removed or kept):
        print(f"imugraph: note: --overwrite: {plural(len(removed), 'session folder', 'session folders')} of the "
              f"earlier run removed" + (f"; kept (other files in them): {', '.join(kept)}" if kept else ""),
              file=sys.stderr)
