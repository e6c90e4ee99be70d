"""`imugraph bench …`: validation benchmarks run from the command line (bench diagnose: the harness of
imugraph.diagnose.harness, options in imugraph.diagnose.bench)."""

from __future__ import annotations

import argparse


def run_bench(args: argparse.Namespace) -> int:
    """Dispatch `imugraph bench <name>`; returns the exit code."""
    if args.bench == "diagnose":
        from imugraph.diagnose.bench import run_bench_diagnose
        return run_bench_diagnose(args)
    raise AssertionError(f"unknown bench {args.bench}")   # argparse only lets known names through
