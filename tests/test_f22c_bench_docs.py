"""Session 22, helper F22c: benchmarks answer --help without running (U22 defect 13) and the docs cite files that
exist (defect 14: a missing test file in docs/diagnose.md, /tmp scripts in docs/stream.md)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _help(script: str, timeout_s: float = 60.0, flag: str = "--help") -> tuple[int, str]:
    """(exit code, output) of `python benchmarks/<script> --help`, in its own process group (killed whole on a
    timeout: run_all.py used to start the suite and its children)."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    proc = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / script), flag], cwd=ROOT, env=env,
                            text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return -1, "timed out: --help started the benchmark"
    return proc.returncode, out


@pytest.mark.parametrize("script", ["run_all.py", "sim_coverage.py", "broad_published.py", "f22c_help_check.py"])
def test_benchmark_answers_help(script):
    code, out = _help(script)
    assert code == 0 and out.lstrip().startswith("usage:"), out[-300:]


def test_run_all_uses_the_readme_stream_solver():
    code, out = _help("run_all.py", flag="--list")
    assert code == 0, out[-300:]
    line = next(ln for ln in out.splitlines() if "stream_speed.py" in ln)
    assert "--lag-solver chain" in line
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "stream_speed.py all --lag 2 --lag-solver chain" in readme


def _doc_texts():
    for p in sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]:
        yield p, p.read_text(encoding="utf-8")


def test_cited_tests_and_benchmarks_exist():
    missing = []
    for p, text in _doc_texts():
        for rel in sorted(set(re.findall(r"\b(?:tests|benchmarks)/[A-Za-z0-9_]+\.py", text))):
            if not (ROOT / rel).is_file():
                missing.append(f"{p.name}: {rel}")
    assert not missing, missing


def test_stream_doc_tmp_scripts_marked_not_kept():
    text = (ROOT / "docs" / "stream.md").read_text(encoding="utf-8")
    unmarked = [m.group(0) for m in re.finditer(r"/tmp/[\w./-]+\.py", text)
                if "not kept" not in text[m.end(): m.end() + 120]]
    assert not unmarked, unmarked


def test_help_texts_name_body_sessions():
    from imugraph.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command" or getattr(a, "choices", None) and
               "mocap" in a.choices).choices
    mocap = " ".join(sub["mocap"].format_help().split())
    diagnose = " ".join(sub["diagnose"].format_help().split())
    assert "x-IMU3 export folders" in mocap and "without magnetometer" in mocap and "--data-dir like SESSION" in mocap
    assert "body session" in diagnose and "session.json" in diagnose
