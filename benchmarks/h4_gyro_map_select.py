"""H4 (issue 2c): the held-out accelerometer test of the gyro map (Options.gyro_map_select) on chosen BROAD
trials: its decision, z, held-out tilt RMS with and without E, and the optical score of the result.

    .venv/bin/python benchmarks/h4_gyro_map_select.py 01,02,04 [--opt FIELD=VALUE ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = pop_opts(argv)
    options = parse_options(["gyro_map_select=True"] + opts)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    for num, s, mask in iter_broad(select):
        t0 = time.process_time()
        est = calibrate(s, options, allow_weak=True)
        cpu = time.process_time() - t0
        rep = est.info.get("gyro_map_select", {})
        tot, inc, head = error_parts(est.quat, s, mask)
        print(f"{num}: keep E {rep.get('keep')} z {rep.get('z', float('nan')):.2f} blocks {rep.get('blocks')} "
              f"carry RMS {json.dumps(rep.get('carry_rms_deg'))}  result {tot:.3f}° (incl {inc:.3f} head "
              f"{head:.3f})  E {np.round(est.calibration.gyro_map.ravel() * 100, 2)} %  {cpu:.1f} s CPU  "
              f"{rep.get('reason', '')}", flush=True)
        for f in rep.get("folds", []):
            print(f"     fold E estimated {f['estimated']}  E % {np.round(np.array(f['E']).ravel() * 100, 2)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
