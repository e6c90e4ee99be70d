"""Median calibrated field norm |D⁻¹(y − o)| of a calibration applied to sessions of its own and of other sensors.

`imugraph.io.validate.check_calibration_applies` refuses a --calibration whose median calibrated norm lies outside
CAL_NORM_RANGE = [0.5, 2]. This prints the median for: the calibration of BROAD trial 01 (estimated here with the
`calibrate` defaults) applied to every BROAD trial (same sensor: must pass) and to Rasteiro's raw sensors (other
sensors: should be refused), and each Rasteiro V_300 sensor's own calibration applied to itself and to the other
Rasteiro sensors. Needs ../shared/data.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/f21a_cal_norm_check.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from imugraph.config import data_dir
from imugraph.errors import ImugraphError
from imugraph.io.validate import calibrated_norm_median

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._usage import no_arguments  # noqa: E402


def main() -> None:
    from imugraph.commands.calibrate import estimate_calibration
    from imugraph.commands.common import Progress
    from imugraph.io.readers import load_session
    from imugraph.io.validate import CAL_NORM_RANGE

    c0 = time.process_time()
    root = data_dir()
    broad = sorted((root / "broad").glob("*.mat"))
    ras_dir = root / "rasteiro" / "DataSets" / "V_300" / "Sequencia1"
    rasteiro = [ras_dir / f"{s}.mat" for s in ("LSM9DS0", "MPU9150", "MPU6050RM3100", "MPU6500RM3100")]
    sessions = {p.stem: load_session(p) for p in broad + rasteiro}
    cals = {}
    for name in [broad[0].stem] + [p.stem for p in rasteiro]:
        try:
            cals[name] = estimate_calibration(sessions[name], 5.0, Progress(quiet=True), allow_weak=True).calibration
        except ImugraphError as exc:
            print(f"# no calibration of {name}: {' '.join(str(exc).split()[:10])}")
    lo, hi = CAL_NORM_RANGE
    print(f"calibration_of applied_to median_norm verdict (refused outside [{lo:g}, {hi:g}])")
    for cname, cal in cals.items():
        for sname, session in sessions.items():
            if cname != broad[0].stem and sname.startswith(("0", "1", "2", "3")) and sname != broad[0].stem:
                continue                    # Rasteiro calibrations: on BROAD 01 only, not every BROAD trial
            med = calibrated_norm_median(session, cal)
            verdict = "pass" if lo <= med <= hi else "refused"
            print(f"{cname} {sname} {med:.3f} {verdict}", flush=True)
    print(f"# cpu {time.process_time() - c0:.1f} s")


if __name__ == "__main__":
    no_arguments(__doc__)          # sys.argv: --help, or no arguments at all
    main()
