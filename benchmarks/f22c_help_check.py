"""Defect 13 of the second acceptance run (U22): does every benchmarks/*.py answer --help without running?

Runs `python benchmarks/X.py --help` for each script (one at a time, in a fresh temporary working folder so that
a script that starts its work instead writes its bench_out/ there, never in the repository) and classifies it:

    help     exit 0 within the time limit, printing "usage" or the first line of its own docstring
    OUTPUT   exit 0 printing something else (ran something short instead, or ignored --help)
    SILENT   exit 0 printing nothing (--help taken as a selection that matched nothing)
    RUNS     still running at the time limit: --help started the benchmark (killed)
    ERROR    a non-zero exit (a traceback, or --help taken for a trial name)
    module   no ``if __name__ == "__main__"``: a helper module, not run

    .venv/bin/python benchmarks/f22c_help_check.py [--timeout S] [--dir DIR] [NAME ...]

--dir: the benchmarks folder to check (default: this one; e.g. a clean clone's, for a before/after).
Prints one line per script and the counts; exit 0.
"""

from __future__ import annotations

import argparse
import os
import resource
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
QUOTES = ('"' * 3, "'" * 3)


def _doc_first_line(text: str) -> str:
    """First non-empty line of the module docstring in `text` ('' without one)."""
    body = text.lstrip()
    if not body.startswith(QUOTES):
        return ""
    lines = [ln.strip() for ln in body[3:].splitlines() if ln.strip()]
    return lines[0][:60] if lines else ""


def check(script: Path, timeout_s: float) -> tuple[str, str]:
    """(verdict, detail) of `script --help` (module docstring)."""
    text = script.read_text(encoding="utf-8", errors="replace")
    if "__main__" not in text:
        return "module", ""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    with tempfile.TemporaryDirectory(prefix="f22c_help_") as cwd:
        # own process group: a script that starts its work (run_all.py: its children too) is killed whole
        proc = subprocess.Popen([sys.executable, str(script), "--help"], cwd=cwd, env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        try:
            stdout, stderr = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            return "RUNS", f"still running after {timeout_s:g} s"
    out = (stdout + stderr).strip()
    last = out.splitlines()[-1][:110] if out else ""
    if proc.returncode != 0:
        return "ERROR", f"exit {proc.returncode}: {last}"
    if not out:
        return "SILENT", "exit 0, printed nothing"
    first = _doc_first_line(text)
    if "usage" in out.lower() or (first and first in out):
        return "help", ""
    return "OUTPUT", f"exit 0: {last}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="f22c_help_check.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--timeout", type=float, default=8.0, help="seconds before a script counts as running (8)")
    ap.add_argument("--dir", default=str(HERE), help="benchmarks folder to check (default: this one)")
    ap.add_argument("names", nargs="*", help="script names (default: every benchmarks/*.py but this one)")
    args = ap.parse_args(argv)
    where = Path(args.dir).resolve()
    scripts = sorted(where / (n if n.endswith(".py") else n + ".py") for n in args.names) if args.names else \
        sorted(p for p in where.glob("*.py") if p.name not in ("__init__.py", Path(__file__).name))
    counts: dict = {}
    for p in scripts:
        verdict, detail = check(p, args.timeout)
        counts[verdict] = counts.get(verdict, 0) + 1
        print(f"{verdict:6s} {p.name:34s} {detail}", flush=True)
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"{len(scripts)} scripts in {where}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) +
          f" (children {ru.ru_utime + ru.ru_stime:.1f} s CPU; killed ones not counted)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
