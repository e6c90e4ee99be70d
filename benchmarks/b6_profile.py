"""CPU profile of calibrate on one BROAD trial (one BLAS thread, cProfile with process_time as its clock).

    .venv/bin/python benchmarks/b6_profile.py TRIAL [--sort tottime|cumtime] [--top N] [--repeat R]
                                                [--top 0] [--opt FIELD=VALUE ...]

Prints the CPU time of calibrate (fastest of R unprofiled runs, each printed) and, unless --top 0, the top
functions of one profiled run. The trial is read before timing.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_v] = "1"

import cProfile  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
import imugraph.calibration.initial  # noqa: E402,F401  (lazy import in calibrate: not profiled)


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt", "--sort", "--top", "--repeat"), max_args=1,
                 values={"--top": int, "--repeat": int})
    opts, rest = pop_opts(argv)
    sort, top, repeat = "tottime", 35, 1
    if "--repeat" in rest:
        i = rest.index("--repeat"); repeat = int(rest[i + 1]); rest = rest[:i] + rest[i + 2:]
    if "--sort" in rest:
        i = rest.index("--sort"); sort = rest[i + 1]; rest = rest[:i] + rest[i + 2:]
    if "--top" in rest:
        i = rest.index("--top"); top = int(rest[i + 1]); rest = rest[:i] + rest[i + 2:]
    if not rest:
        usage_error("expected one TRIAL (e.g. 24)")
    check_trials({rest[0]})
    options = parse_options(opts)
    _, s, _ = next(iter_broad({rest[0]}))
    cpus = []
    for _ in range(repeat):                         # plain runs: the CPU time without profiler overhead
        c0 = time.process_time()
        calibrate(s, options, allow_weak=True)
        cpus.append(time.process_time() - c0)
    print(f"calibrate CPU {min(cpus):.2f} s (fastest of {', '.join(f'{c:.2f}' for c in cpus)}; unprofiled)",
          flush=True)
    if top == 0:
        return 0
    prof = cProfile.Profile(time.process_time)
    prof.enable()
    calibrate(s, options, allow_weak=True)
    prof.disable()
    pstats.Stats(prof).sort_stats(sort).print_stats(top)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
