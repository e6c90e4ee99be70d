"""H9 (issue 2c): would held-out MAGNETOMETER prediction (calibration/field_select.select, the precedent of
Options.field_select) choose between the velocity processes? Candidates are Options variants of
estimate_velocity_process; the first is the reference (chosen unless another beats it by paired z ≥ 2 over the
2 s blocks). Prints per trial the scores, z, the choice, and each candidate's error on all data (optical truth:
scoring only).

    .venv/bin/python benchmarks/h9_mag_select.py 02,07 [--variants bounded_ar2,free_ar2]
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, pop_value  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration import field_select, ml  # noqa: E402


@dataclass(frozen=True)
class VelocityCandidate:
    """A velocity process to score (field_select's Candidate interface: apply, label)."""

    mode: str

    def apply(self, options):
        return replace(options, estimate_velocity_process=self.mode, field_select=False)

    def label(self) -> str:
        return self.mode


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--variants",), max_args=1)
    variants, argv = pop_value(argv, "--variants", "bounded_ar2,free_ar2")
    variants = variants.split(",")
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    cands = tuple(VelocityCandidate(m) for m in variants)
    for num, s, mask in iter_broad(select):
        t0 = time.process_time()
        best, table, init = field_select.select(s, ml.Options(), cands, allow_weak=True)
        cpu = time.process_time() - t0
        errs = {c.mode: error_parts(ml.calibrate(s, c.apply(ml.Options()), initial=init, allow_weak=True).quat,
                                    s, mask)[0] for c in cands}
        print(f"{num} chosen {best.label():12s} ({cpu:.1f} s CPU for the folds)  " + "  ".join(
            f"{r['candidate'].label()}: score {r['score']:.3e} z {r.get('z', 0):+.2f} err {errs[r['candidate'].mode]:.3f}°"
            for r in table), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
