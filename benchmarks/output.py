"""Result files of the benchmarks: bench_out/<name>.json beside the repository root, written atomically.

NaN and ±inf (a method that failed on a trial) become JSON null; numpy scalars and arrays become plain
numbers and lists, so the files are strict JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

from imugraph.io.writers import atomic_write_text, json_ready

OUT_DIR = Path(__file__).resolve().parents[1] / "bench_out"


def write_json(name: str, payload: dict) -> Path:
    """Write bench_out/<name> atomically (strict JSON, indented) and return its path."""
    text = json.dumps(json_ready(payload), indent=1, allow_nan=False)
    return atomic_write_text(OUT_DIR / name, text + "\n")
