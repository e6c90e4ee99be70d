"""Session 23 (helper D23): the body harness's verdicts side by side for an option off vs on.

Reads two result files of `benchmarks/diagnose_body.py` (bench_out/<out>, the same --hosts, --duration and --seed:
the same injected cases) and prints per case the verdict and sensor, the held-out shrink of the verdict's effect,
the soft-tissue window IoU and the CPU of each run, then the counts (clean `none`, correct per label) and the
CPU totals. A case whose verdict or sensor differs is marked "≠".

    .venv/bin/python benchmarks/diagnose_body.py --hosts xsens_lower,cmu_lower,xsens_full,real_walk --duration 20 \
        --seed 0 --out d23_h16_off_s0.json
    .venv/bin/python benchmarks/diagnose_body.py ... --seed 0 --opt FIELD=VALUE ... --out d23_h16_on_s0.json
    .venv/bin/python benchmarks/d23_verdicts.py d23_h16_off_s0.json d23_h16_on_s0.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _load(name: str) -> list:
    from benchmarks.output import OUT_DIR
    p = Path(name) if Path(name).exists() else OUT_DIR / name
    return json.loads(p.read_text())["records"]


def _fmt(x, nd=2) -> str:
    return "—" if x is None else f"{x:.{nd}f}"


def _counts(recs: list) -> dict:
    ok = {}
    for r in recs:
        good = r["verdict"] == r["label"] and (r["sensor_hit"] if r["label"] != "none" else True)
        ok.setdefault(r["label"], [0, 0])
        ok[r["label"]][0] += int(good)
        ok[r["label"]][1] += 1
    return ok


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("off")
    p.add_argument("on")
    a = p.parse_args(argv)
    off, on = _load(a.off), _load(a.on)
    key = {(r["host"], r["label"]): r for r in on}
    n_diff = 0
    print(f"{'host':<12} {'label':<19} {'off: verdict/sensor':<34} {'on: verdict/sensor':<34} "
          f"{'shrink off/on':<13} {'IoU off/on':<11} CPU off/on")
    for r in off:
        s = key.get((r["host"], r["label"]))
        if s is None:
            print(f"{r['host']:<12} {r['label']:<19} missing in {a.on}")
            continue
        same = (r["verdict"], r["sensor"]) == (s["verdict"], s["sensor"])
        n_diff += not same
        print(f"{r['host']:<12} {r['label']:<19} {r['verdict'] + '/' + str(r['sensor']):<34} "
              f"{s['verdict'] + '/' + str(s['sensor']):<32}{'  ' if same else '≠ '} "
              f"{_fmt(r['shrink'])}/{_fmt(s['shrink']):<8} {_fmt(r.get('window_iou'))}/{_fmt(s.get('window_iou')):<6} "
              f"{r['cpu_s']:.1f}/{s['cpu_s']:.1f}")
    co, cn = _counts(off), _counts(on)
    print("correct per label (off → on): " + ", ".join(f"{k} {co[k][0]}/{co[k][1]} → {cn.get(k, [0])[0]}/{co[k][1]}"
                                                       for k in co))
    print(f"{n_diff} case(s) with another verdict or sensor; CPU total {sum(r['cpu_s'] for r in off):.1f} → "
          f"{sum(r['cpu_s'] for r in on):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
