"""`imugraph bench …`: validation benchmarks run from the command line (bench diagnose: the harness of
imugraph.diagnose.harness, options in imugraph.diagnose.bench).

`bench diagnose --trials LIST` names BROAD trials; a trial with no `<NN>_*.mat` in the BROAD folder is refused
(it used to be dropped silently: `--trials 01,99` ran on 01 alone), and a missing BROAD folder is said in one
warning line (the run then uses the --sims simulations only).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def check_trials(args: argparse.Namespace) -> list[str]:
    """The --trials names, each present in the BROAD folder (data_dir/broad, else imugraph.config.broad_dir()).

    Returns:
        The trial names (may be empty).

    Raises:
        SessionError: a named trial without a `<name>_*.mat` file in an existing BROAD folder (field 'trials').
    """
    from imugraph.config import broad_dir
    from imugraph.errors import SessionError

    trials = [t.strip() for t in (getattr(args, "trials", "") or "").split(",") if t.strip()]
    data_dir = getattr(args, "data_dir", None)
    root = Path(data_dir).expanduser() / "broad" if data_dir else broad_dir()
    if not trials:
        return trials
    if not root.is_dir():
        print(f"imugraph: warning: --trials {','.join(trials)}: no BROAD folder at {root}; only the simulated "
              "sessions (--sims) are used", file=sys.stderr, flush=True)
        return trials
    missing = [t for t in trials if not any(root.glob(f"{t}_*.mat"))]
    if missing:
        have = sorted({p.name.split("_", 1)[0] for p in root.glob("*_*.mat")})
        raise SessionError(str(root), "trials", f"{', '.join(missing)} (no <trial>_*.mat there)",
                           f"trial numbers among {', '.join(have)}")
    return trials


def run_bench(args: argparse.Namespace) -> int:
    """Dispatch `imugraph bench <name>`; returns the exit code."""
    if args.bench == "diagnose":
        from imugraph.diagnose.bench import run_bench_diagnose
        check_trials(args)
        return run_bench_diagnose(args)
    raise AssertionError(f"unknown bench {args.bench}")   # argparse only lets known names through
