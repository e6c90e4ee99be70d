"""The harness's hosts for the task-E probes (e5_magnet_window.py, e5_saturation.py): the same crops of BROAD
01 02 04 06 07 and two simulations that `imugraph bench diagnose --n 2` draws from, for one seed."""
from __future__ import annotations

import argparse

from imugraph.diagnose.bench import DEFAULT_TRIALS, harness_sessions


def harness_hosts(doc: str, case: str) -> tuple[argparse.Namespace, list]:
    """Parse --seed/--cases/--duration (default case `case`) and build the harness's host sessions."""
    ap = argparse.ArgumentParser(description=doc)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cases", default=case)
    ap.add_argument("--duration", type=float, default=60.0)
    a = ap.parse_args()
    sessions = harness_sessions(argparse.Namespace(trials=",".join(DEFAULT_TRIALS), duration=a.duration,
                                                   seed=a.seed, sims=2))
    return a, sessions
