"""Probe (S16-F): why the harness' vibration cases are missed or not shrunk.

Re-draws the harness cases of a seed exactly as `imugraph.diagnose.harness.run_harness` does (same rng
sequence, same hosts), and for the selected case ids prints: the injected truth, the vibration effect's
window search on the base fit (above-band power vs its quiet level), the base residual's above-band RMS
in/out of the true window, and the diagnosis' per-effect lines (screen + refit).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/f5_vibration_probe.py --seed 2 --cases 015,016
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def draw_cases(args):
    """[(case id, injected session, truth name, truth)] in the harness' order (harness.draw_cases)."""
    from imugraph.diagnose import harness
    from imugraph.diagnose.bench import harness_sessions
    from imugraph.diagnose.effects import EFFECTS

    cases = harness.draw_cases(harness_sessions(args), list(EFFECTS), args.n, np.random.default_rng(args.seed))
    return [(cid, inj, name, truth) for cid, _host, inj, name, truth in cases]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--cases", default="015,016")
    p.add_argument("--trials", default="01,02,04,06,07")
    p.add_argument("--sims", type=int, default=2)
    p.add_argument("--n", type=int, default=2)
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--no-diagnose", action="store_true", help="window search only")
    p.add_argument("--vibration-band-windows", action=argparse.BooleanOptionalAction, default=None,
                   help="DiagnoseOptions.vibration_band_windows (S16-F)")
    args = p.parse_args(argv)
    from imugraph.diagnose.effects.vibration import EFFECT as VIB, above_motion_band
    from imugraph.diagnose.fit import base_options, fit_base
    from imugraph.diagnose.run import DiagnoseOptions, diagnose

    keep = {c.strip().zfill(3) for c in args.cases.split(",")}
    for cid, sess, name, truth in draw_cases(args):
        if cid not in keep:
            continue
        print(f"== case {cid} {sess.name} truth {name} {truth.get('params')} window "
              f"({truth.get('t_start', float('nan')):.2f}, {truth.get('t_end', float('nan')):.2f}) "
              f"rate {sess.rate:.1f} t0 {sess.t[0]:.2f} t1 {sess.t[-1]:.2f}")
        real = fit_base(sess, base_options(5.0))
        hp = above_motion_band(real.residuals["acc"], sess.rate)
        if "t_start" in truth:
            ins = (sess.t >= truth["t_start"]) & (sess.t <= truth["t_end"])
            print(f"   acc σ {np.round(np.asarray(real.sigma['acc']), 3)}; above-band RMS per axis in "
                  f"{np.round(np.sqrt(np.mean(hp[ins] ** 2, 0)), 3)} out {np.round(np.sqrt(np.mean(hp[~ins] ** 2, 0)), 3)}")
        print(f"   find_windows: {[(round(a, 2), round(b, 2)) for a, b in VIB.find_windows(real)]}")
        if args.no_diagnose:
            continue
        opt = DiagnoseOptions()
        if args.vibration_band_windows is not None:
            from dataclasses import replace
            opt = replace(opt, vibration_band_windows=args.vibration_band_windows)
        d = diagnose(sess, opt, progress=lambda m: print("   " + m))
        print(f"   verdict {d.verdict}")
        for r in d.effects:
            if r.name == "vibration" or r.name == d.verdict:
                print(f"   {r.name} [{r.stage}] significant {r.significant} support {r.support_fraction:.2f} "
                      f"raw_before {r.raw_before:.3f} floor {r.floor:.3f} gap {r.gap_before:.3f} → {r.gap_after:.3f} "
                      f"log score {r.loglik_gain:+.4f} per channel "
                      f"{ {c: round(v, 4) for c, v in (r.loglik_per_channel or {}).items()} } folds "
                      f"{[round(f, 4) for f in (r.loglik_folds or [])]} window ({r.t_start}, {r.t_end}) "
                      f"band {(r.params or {}).get('band_hz')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
