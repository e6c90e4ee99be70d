"""`imugraph diagnose SESSION --out DIR`: where the sim-to-real gap lies, which unmodelled effect explains
it and how far it shrinks (imugraph.diagnose.run.diagnose); writes diagnosis.json, diagnosis.md,
gap_over_time.png and residuals.png, and prints a short summary.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imugraph.commands import common


def run_diagnose(args: argparse.Namespace) -> int:
    """diagnose SESSION [--out DIR] [--keyframe-hz HZ] [--seed N] [--effects a,b] [--data-dir DIR] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    from imugraph.diagnose.report import summary_table, write_report
    from imugraph.diagnose.run import DiagnoseOptions, diagnose

    progress = common.Progress(getattr(args, "quiet", False))
    path = common.resolve_session_path(args.session, getattr(args, "data_dir", None))
    session = common.load(path, progress)
    out = common.out_dir_for(getattr(args, "out", None), Path(path).stem)
    names = getattr(args, "effects", None)
    options = DiagnoseOptions(keyframe_hz=float(getattr(args, "keyframe_hz", 5.0) or 5.0),
                              seed=int(getattr(args, "seed", 0) or 0),
                              effects=tuple(n.strip() for n in names.split(",") if n.strip()) if names else None)
    with progress.library_output():
        diag = diagnose(session, options, progress=progress.say)
    paths = write_report(diag, out)
    progress.say(f"wrote {', '.join(sorted(paths))} in {out}")
    print(summary_table(diag))
    return 0
