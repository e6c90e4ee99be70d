"""`imugraph batch SESSIONS… --out DIR [--scheduler ADDRESS] [--workers N]`: many sessions on Dask.

Each session is calibrated and smoothed on a worker (`imugraph.batch.run_one`), into DIR/<session
stem>/ with the files of `imugraph calibrate`. A progress bar and one line per failed session go to
stderr; the summary table goes to stdout and to DIR/summary.json + DIR/summary.csv (written atomically).

Exit status: 0 every session ok; 1 at least one session failed (the others still ran and are written);
2 the batch could not run (bad arguments, --out not writable, scheduler not answering, local cluster not
starting); 130 Ctrl-C: the unfinished sessions cancelled, the cluster closed, DIR/summary.json (+ .csv) written
for the sessions that had finished ("interrupted": true), one line "imugraph: interrupted (…)" on stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict
from pathlib import Path

from imugraph.commands import common

EXIT_SOME_FAILED = 1
EXIT_INTERRUPTED = 130     # as imugraph.cli: Ctrl-C (after summary.json of the finished sessions is written)


def run_batch_command(args: argparse.Namespace) -> int:
    """batch SESSIONS… --out DIR [--scheduler ADDRESS] [--workers N] [--keyframe-hz HZ] [--allow-weak]
    [--gyro-scale | --no-gyro-scale] [--data-dir DIR] [--quiet].

    Returns:
        0 when every session succeeded, 1 when any failed (errors that stop the whole batch are raised
        as ImugraphError and reported by `imugraph.cli.main` with exit status 2).
    """
    from imugraph.batch import BatchInterrupted, run_batch, summary_table, write_summary
    from imugraph.commands.calibrate import CalibrateOptions

    paths = [common.resolve_session_path(s, args.data_dir, strict=False) for s in args.sessions]
    options = CalibrateOptions(args.keyframe_hz, args.allow_weak, getattr(args, "gyro_scale", None))
    if args.scheduler and args.workers and not args.quiet:
        print("imugraph: note: --workers applies to the local cluster only; ignored with --scheduler",
              file=sys.stderr)
    where = f"the scheduler at {args.scheduler}" if args.scheduler else \
        f"a local cluster of {args.workers or 'CPU-count'} worker processes"
    common.Progress(args.quiet).say(f"{len(paths)} sessions on {where} → {args.out}")
    start = time.perf_counter()
    meta = {"scheduler": args.scheduler, "workers": args.workers, "options": asdict(options)}
    try:
        rows = run_batch(paths, args.out, scheduler=args.scheduler, workers=args.workers, options=options,
                         progress=not args.quiet)
    except BatchInterrupted as stop:     # Ctrl-C: tasks cancelled, cluster closed; the finished sessions summarised
        meta.update(wall_s=time.perf_counter() - start, interrupted=True, sessions_requested=stop.total)
        js, _ = write_summary(Path(args.out).expanduser(), stop.rows, meta)
        print(f"imugraph: interrupted ({len(stop.rows)} of {stop.total} sessions finished; summary in {js})",
              file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    wall = time.perf_counter() - start
    meta = {"wall_s": wall, **meta}
    js, csv_path = write_summary(Path(args.out).expanduser(), rows, meta)
    print(summary_table(rows))
    print(f"wall time {wall:.1f} s; summary in {js} and {csv_path}")
    return 0 if all(r["status"] == "ok" for r in rows) else EXIT_SOME_FAILED
