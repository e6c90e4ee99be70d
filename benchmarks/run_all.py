"""`make bench`: the benchmarks of the foundation issue, each printing its own table.

    sim_coverage.py      simulated truth within reported std; noise levels         (issue 2a)
    broad_published.py   BROAD trials as published vs offline VQF / VQF + timing   (issue 2c, 2e)
    broad_known_distortion.py  BROAD with a known seeded affine distortion of the magnetometer  (issue 2b)
    rasteiro.py          raw uncalibrated magnetometers vs robot arm: field norm, heading    (issue 2d)
    speed.py             calibrate+smooth / smooth with known calibration vs offline VQF   (issue 2e)
    peer_table.py        the peers alone (checks the metric against the data README)
    batch_scaling.py     `imugraph batch` on the BROAD trials, 1 vs 2 worker processes (issue 3)
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    rc = 0
    for script, args in (("peer_table.py", []), ("sim_coverage.py", ["50", "60", "100"]),
                         ("broad_published.py", []), ("broad_known_distortion.py", []),
                         ("rasteiro.py", []), ("speed.py", []), ("batch_scaling.py", [])):
        print(f"\n=== {script} {' '.join(args)} ===", flush=True)
        rc |= subprocess.call([sys.executable, str(HERE / script), *args])
    return rc


if __name__ == "__main__":
    sys.exit(main())
