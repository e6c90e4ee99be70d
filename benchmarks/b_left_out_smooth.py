"""`smooth --calibration` with the rows the calibration's solve left out (calibration.json `left_out`) vs without.

Per BROAD trial: calibrate (Options(window_trial_verdict=True) unless --opt says otherwise), write and read
calibration.json, then smooth_fixed (what `imugraph smooth --calibration` runs) with the file as read and with
its `left_out` runs removed (the file before they were exported); RMS orientation error over `movement`
(broad_published.py's score) of calibrate's own output and of both smooths, and the rows left out.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/b_left_out_smooth.py [TRIALS] [--opt FIELD=VALUE ...]
"""

from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402
from imugraph.graphs.cpp_smoother import smooth_fixed  # noqa: E402
from imugraph.io.writers import read_calibration_json, write_calibration_json  # noqa: E402


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = pop_opts(argv)
    options = parse_options(opts or ["window_trial_verdict=True"])
    select = set(argv[0].split(",")) if argv else {"32", "34"}
    check_trials(select)
    for _num, s, mask in iter_broad(select):
        est = calibrate(s, options, allow_weak=True)
        with tempfile.TemporaryDirectory() as tmp:
            cal = read_calibration_json(write_calibration_json(Path(tmp) / "calibration.json", est.calibration))
        stripped = replace(cal, disturbances=[{**d, "left_out": []} for d in cal.disturbances])
        n_out = int(np.sum(np.any(np.isnan(cal.corrected(s.t, s.mag)), axis=1)
                           & ~np.any(np.isnan(stripped.corrected(s.t, s.mag)), axis=1)))

        def err(q):
            return round(orientation_error(q, s.quat, mask, s.rate).rms_deg, 3)
        print(json.dumps({"trial": s.name[:2], "calibrate_deg": err(est.quat),
                          "smooth_file_deg": err(smooth_fixed(s, cal)),
                          "smooth_without_left_out_deg": err(smooth_fixed(s, stripped)),
                          "left_out_rows": n_out,
                          "left_out_runs": [len(d.get("left_out", [])) for d in cal.disturbances]}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
