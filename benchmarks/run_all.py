"""`make bench`: the benchmarks of the foundation issue, each printing its own table.

    sim_coverage.py      simulated truth within reported std; noise levels         (issue 2a)
    broad_published.py   BROAD trials as published vs offline VQF / VQF + timing   (issue 2c, 2e)
    peer_table.py        the peers alone (checks the metric against the data README)
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    rc = 0
    for script, args in (("peer_table.py", []), ("sim_coverage.py", ["50", "60", "100"]),
                         ("broad_published.py", [])):
        print(f"\n=== {script} {' '.join(args)} ===", flush=True)
        rc |= subprocess.call([sys.executable, str(HERE / script), *args])
    return rc


if __name__ == "__main__":
    sys.exit(main())
