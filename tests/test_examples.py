"""The documented examples run as a user would run them."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_stream_push_example_runs_and_reports_no_failed_update():
    out = subprocess.run([sys.executable, str(ROOT / "examples" / "stream_push.py")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "'failed_updates': 0" in out.stdout
    assert "calibration refits" in out.stdout
