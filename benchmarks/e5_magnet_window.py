"""Task E (session 16): why the magnet window of a harness case is mis-placed — the windows found on the
base fit (`find_windows`: the step search (M3) and the energy detector), and per refit round.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/e5_magnet_window.py --seed 1 --cases 001
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.e5_hosts import harness_hosts  # noqa: E402
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects import magnetic_disturbance as md
from imugraph.diagnose.fit import base_options, fit_base
from imugraph.diagnose.harness import run_harness
from imugraph.diagnose.refit import refit_effect


def main() -> None:
    a, sessions = harness_hosts(__doc__, "001")

    def fn(s):
        print(s.name, "t0", round(float(s.t[0]), 2), "t1", round(float(s.t[-1]), 2), flush=True)
        real = fit_base(s, base_options(5.0))
        bRn = np.transpose(real.nRb, (0, 2, 1))
        earth = float(np.median(np.linalg.norm((bRn @ real.calibration.n_mag) @ np.asarray(real.calibration.D).T, axis=1)))
        sw = md.step_windows(s.t, real.residuals["mag"], earth)
        print("  |m| (model)", round(earth, 3))
        for i0, i1, lr, step in sw:
            print(f"  step window {s.t[i0]:.2f}-{s.t[min(i1, len(s.t)) - 1]:.2f} LR {lr:.0f} |step| {np.linalg.norm(step) / earth:.2f} |m|")
        for i0, i1 in md.step_windows_refit(real, real.residuals["mag"], earth)[0]:
            print(f"  (M3') step window {s.t[i0]:.2f}-{s.t[min(i1, len(s.t)) - 1]:.2f}")
        old = md.STEP_REFIT
        try:
            for flag in (False, True):
                md.STEP_REFIT = flag
                print(f"  STEP_REFIT={flag} find_windows",
                      [(round(x, 2), round(y, 2)) for x, y in md.EFFECT.find_windows(real)])
                ext, info = refit_effect(md._ALTERNATION, real, 2, None)
                for k, r in enumerate(info["rounds"]):
                    print(f"    refit round {k}: windows",
                          [(round(w["t_start"], 2), round(w["t_end"], 2)) for w in r["params"]["windows"]])
        finally:
            md.STEP_REFIT = old
        return {"verdict": "none", "effects": [], "gap": {}}

    run_harness(sessions, list(EFFECTS), 2, np.random.default_rng(a.seed), diagnose_fn=fn,
                only=a.cases.split(","), clean=False)


if __name__ == "__main__":
    main()
