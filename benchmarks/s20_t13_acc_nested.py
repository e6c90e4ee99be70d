"""Run another benchmark with (T13) on the accelerometer only and the nested check (V'') on (docs/diagnose.md §S20-L).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/s20_t13_acc_nested.py benchmarks/w20_body_worn.py
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/s20_t13_acc_nested.py benchmarks/diagnose_harness.py --n 2 --duration 60 --seed 0

The module flags are set before the script runs; the diagnoses' options leave them as set (None).
"""
import runpy
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._usage import exit_on_help, usage_error  # noqa: E402


def main(argv: list[str]) -> None:
    """Set the flags, then run SCRIPT as __main__ with the rest of argv (its own --help stays its own)."""
    exit_on_help(__doc__, argv[:1])                 # only the first argument: `SCRIPT --help` is SCRIPT's help
    if not argv or not Path(argv[0]).is_file():
        usage_error(f"expected a benchmark script to run, got {' '.join(argv[:1]) or 'nothing'}")
    from imugraph.diagnose import nested
    from imugraph.diagnose.effects import time_offset

    time_offset.SHIFT_PREDICTION = True
    time_offset.SHIFT_PREDICTION_CHANNELS = ("acc",)
    nested.NESTED_CHECK = True
    sys.argv = argv
    runpy.run_path(argv[0], run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
