"""Benchmark: the diagnosis' validation harness (same as `imugraph bench diagnose`).

Injects every effect of imugraph.diagnose.effects (randomised parameters and windows) into undisturbed
BROAD rotation trials and simulations, diagnoses blind, prints the confusion matrix, top-1, window IoU and
held-out gap shrink, and writes harness.json / harness.md under --out.

    .venv/bin/python benchmarks/diagnose_harness.py --n 2 --duration 60
"""

from __future__ import annotations

import argparse
import sys

from imugraph.diagnose.bench import add_arguments, run_bench_diagnose


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    return run_bench_diagnose(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
