"""Run another benchmark with (T13) on the accelerometer only and the nested check (V'') on (docs/diagnose.md §S20-L).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/s20_t13_acc_nested.py benchmarks/w20_body_worn.py
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/s20_t13_acc_nested.py benchmarks/diagnose_harness.py --n 2 --duration 60 --seed 0

The module flags are set before the script runs; the diagnoses' options leave them as set (None).
"""
import runpy, sys
from imugraph.diagnose.effects import time_offset
from imugraph.diagnose import nested
time_offset.SHIFT_PREDICTION = True
time_offset.SHIFT_PREDICTION_CHANNELS = ("acc",)
nested.NESTED_CHECK = True
script = sys.argv[1]
sys.argv = sys.argv[1:]
runpy.run_path(script, run_name="__main__")
