"""Command-line hygiene for the benchmarks that read sys.argv by hand (session 23, helper M23; U22 defect 13).

`--help` (or `-h`) anywhere on the command line prints `usage: <the docstring's command line>` and the script's
docstring, then exits 0 before anything runs. A flag the script does not know, or a trial selection that names no
BROAD trial, is a one-line error on stderr with exit 2 — never a traceback, never a silent run that matches nothing.
Valid command lines are untouched: these checks only read argv.

    from benchmarks._usage import exit_on_help, usage_error, check_trials
    exit_on_help(__doc__, argv, flags=("--opt", "--tag"))      # first thing in main(argv)
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

HELP = ("-h", "--help")
_FLAG = re.compile(r"^--?[A-Za-z]")          # "-x", "--name"; not "-1", "-0.5" (negative numbers are values)


def _prog() -> str:
    return Path(sys.argv[0]).name or "benchmark"


def usage_text(doc: str | None, prog: str | None = None) -> str:
    """`usage: benchmarks/NAME.py ARGS` (the first command line the docstring gives for this script) and the docstring.

    Without a command line in the docstring the usage line is `benchmarks/NAME.py` alone (no arguments)."""
    prog = prog or _prog()
    doc = (doc or "").strip()
    key = f"benchmarks/{prog}"
    cmds = [ln.strip() for ln in doc.splitlines() if key in ln]
    usage = cmds[0][cmds[0].index(key):].rstrip("\\ `") if cmds else key
    return f"usage: {usage}\n\n{doc}\n" if doc else f"usage: {usage}\n"


def usage_error(message: str, prog: str | None = None) -> None:
    """One line `PROG: error: MESSAGE (see --help)` on stderr, exit 2 (argparse's convention)."""
    print(f"{prog or _prog()}: error: {message} (see --help)", file=sys.stderr)
    raise SystemExit(2)


def exit_on_help(doc: str | None, argv: Sequence[str] | None = None, flags: Iterable[str] | None = None,
                 switches: Iterable[str] = (), max_args: int | None = None,
                 values: Mapping[str, Callable] | None = None) -> None:
    """Handle `--help` and reject unknown flags before a hand-parsed benchmark starts its work.

    Args:
        doc: the script's module docstring (printed by --help).
        argv: the arguments (default sys.argv[1:]).
        flags: the flags the script understands that take a value (`--opt FIELD=VALUE`); None: nothing is checked
            but --help.
        switches: the flags it understands that take none (`--halves`).
        max_args: the most positional items argv may hold (items that are neither a known flag, a value right after
            a flag in `flags`, nor a switch); None: no limit.
        values: flag → converter (int, float, floats) of its value; a value it cannot convert is a usage error.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in HELP for a in argv):
        print(usage_text(doc), end="")
        raise SystemExit(0)
    if flags is None:
        return
    takes_value, switches = set(flags), set(switches)
    known = takes_value | switches
    free, i = [], 0
    while i < len(argv):
        a = argv[i]
        if _FLAG.match(a) and a not in known:       # `--opt=X` too: these parsers read `--opt X` only
            usage_error(f"unrecognized argument {a!r}; known flags: {' '.join(sorted(known)) or 'none'}")
        if a in takes_value:
            if i + 1 >= len(argv):
                usage_error(f"{a} expects a value")
            convert = (values or {}).get(a)
            if convert is not None:
                try:
                    convert(argv[i + 1])
                except ValueError:
                    kind = {int: "an integer", float: "a number"}.get(convert) or convert.__doc__ or convert.__name__
                    usage_error(f"{a} {argv[i + 1]!r}: expected {kind}")
            i += 2
            continue
        if a not in switches:
            free.append(a)
        i += 1
    if max_args is not None and len(free) > max_args:
        usage_error(f"unexpected argument(s) {' '.join(free[max_args:])!r}")


def floats(text: str) -> list[float]:
    """comma-separated numbers"""
    return [float(x) for x in text.split(",")]


def no_arguments(doc: str | None, argv: Sequence[str] | None = None) -> None:
    """For a benchmark that takes no arguments: --help as `exit_on_help`, any other argument a usage error."""
    argv = list(sys.argv[1:] if argv is None else argv)
    exit_on_help(doc, argv)
    if argv:
        usage_error(f"takes no arguments, got {' '.join(argv)!r}")


def check_trials(select: Iterable[str] | None, what: str = "BROAD trial") -> None:
    """Exit 2 with one line when a trial selection (two-digit numbers, e.g. {"02", "15"}) names no BROAD trial
    present; None or empty (every trial) passes. Reads only the folder listing."""
    if not select:
        return
    from benchmarks.common import broad_trials

    select = set(select)
    have = {p.name[:2] for p in broad_trials()}
    if not select & have:
        usage_error(f"no {what} matches {','.join(sorted(select))} (expected two-digit numbers like "
                    f"{','.join(sorted(have)[:3]) or '01,02'}{',...' if have else '; no BROAD data found'})")
