"""Benchmark (issue 5, §S17-H): replay harness cases (same draw as benchmarks/diagnose_harness.py with the
same --seed) and print every effect's decision numbers in full: stage, (A2), (A1), the log score (A4') per
channel and per fold, the joint fit's own scores (J5)/(J6), size, significant, relevant.

    .venv/bin/python benchmarks/m5_case.py --seed 1 --cases 013 [model switches of diagnose_harness.py]
"""

from __future__ import annotations

import argparse
import sys


def _f(x, f="{:+.3f}"):
    try:
        return f.format(float(x))
    except (TypeError, ValueError):
        return "–"


def main(argv=None) -> int:
    from imugraph.diagnose.bench import add_arguments, diagnose_options, harness_run, harness_sessions
    from imugraph.diagnose.run import diagnose

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    a = p.parse_args(argv)
    sessions = harness_sessions(a)
    o = diagnose_options(a)
    kept = []

    def fn(session):
        d = diagnose(session, o)
        kept.append(d.to_json())
        return d

    rep = harness_run(a, sessions, fn)
    for case, d in zip(rep["cases"], kept):
        print(f"case {case['case']} {case['session']}: truth {case['truth']} {case['truth_params']} → {case['verdict']}")
        for e in d["effects"]:
            s = e.get("size") or {}
            per = e.get("loglik_gain_per_channel") or {}
            print(f"  {e['name']:<21} [{e['stage']}] ch {e['channel']} A2 {_f(e['penalised_shrink'], '{:+.2f}')} "
                  f"A1 {_f(e['shrink'], '{:+.2f}')} A4 {_f(e['loglik_gain'])} "
                  f"(gyr {_f(per.get('gyr'))} acc {_f(per.get('acc'))} mag {_f(per.get('mag'))}) folds "
                  f"[{' '.join(_f(x, '{:+.2f}') for x in e.get('loglik_gain_per_fold') or [])}]"
                  + (f" J5 {_f(e.get('own_cost_gain'))} folds [{' '.join(_f(x, '{:+.3f}') for x in e.get('own_cost_gain_per_fold') or [])}]"
                     f" J6 {_f(e.get('own_cost_shrink'), '{:+.2f}')} J5/ch "
                     + " ".join(f"{c} {_f((e.get('own_cost_gain_per_channel') or {}).get(c), '{:+.4f}')}"
                                f"/{_f((e.get('own_excess_per_channel') or {}).get(c), '{:+.4f}')}"
                                for c in ("gyr", "acc", "mag")) if e.get("own_cost_gain_per_fold") else "")
                  + f" size {_f(s.get('value'), '{:.3g}')}/{_f(s.get('threshold'), '{:.3g}')}"
                  f" per fold [{' '.join(_f(x, '{:.3g}') for x in e.get('size_per_fold') or [])}]"
                  f" {'S' if e['significant'] else 's'}{'R' if e['relevant'] else 'r'}"
                  + (f" screen A2 {_f(e['screen'].get('penalised_shrink'), '{:+.2f}')}" if e.get("screen") else ""),
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
