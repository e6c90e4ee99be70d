"""Result files of the benchmarks: bench_out/<name>.json beside the repository root, written atomically.

NaN and ±inf (a method that failed on a trial) become JSON null; numpy scalars and arrays become plain
numbers and lists, so the files are strict JSON.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from imugraph.io.writers import atomic_write_text

OUT_DIR = Path(__file__).resolve().parents[1] / "bench_out"


def plain(obj: Any) -> Any:
    """obj with numpy values turned into Python ones and non-finite floats into None (recursively)."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    return obj


def write_json(name: str, payload: dict) -> Path:
    """Write bench_out/<name> atomically (strict JSON, indented) and return its path."""
    text = json.dumps(plain(payload), indent=1, allow_nan=False)
    return atomic_write_text(OUT_DIR / name, text + "\n")
