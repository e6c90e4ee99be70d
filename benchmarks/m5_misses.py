"""Benchmark (issue 5, §S17-H): every miss of one or more harness runs as a table — case, host, injected
effect and parameters, verdict, and the decision numbers of the top-3 effects ((A2) penalised shrink, the
log score (A4') or the joint fit's own cost gain (J5) with its worst fold, size/threshold, significant,
relevant). Reads the harness.json files written by benchmarks/diagnose_harness.py (its `scores` field).

    .venv/bin/python benchmarks/m5_misses.py DIR [DIR ...]
    .venv/bin/python benchmarks/m5_misses.py --diff BEFORE_DIR AFTER_DIR   (verdict changes between two runs)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _fmt(x, f="{:.3g}"):
    return "–" if x is None else f.format(x)


def _params(p: dict) -> str:
    out = []
    for k, v in (p or {}).items():
        if isinstance(v, float):
            out.append(f"{k}={v:.3g}")
        elif isinstance(v, (int, str)):
            out.append(f"{k}={v}")
        elif isinstance(v, list) and len(v) <= 3 and all(isinstance(x, (int, float)) for x in v):
            out.append(f"{k}=[{', '.join(f'{x:.3g}' for x in v)}]")
    return "; ".join(out)


def effect_line(s: dict) -> str:
    """One effect's decision numbers, compact."""
    gain = s.get("own_gain") if s.get("own_gain") is not None else s.get("loglik_gain")
    tag = "J5" if s.get("own_gain") is not None else "A4"
    flags = ("S" if s.get("significant") else "s") + ("R" if s.get("relevant") else "r")
    return (f"{s['name']}[{(s.get('stage') or '?')[0]}] A2 {_fmt(s.get('penalised'), '{:+.2f}')} "
            f"{tag} {_fmt(gain, '{:+.3f}')} minfold {_fmt(s.get('min_fold'), '{:+.3f}')} "
            f"size {_fmt(s.get('size'))}/{_fmt(s.get('threshold'))} {flags}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dirs", nargs="*", help="harness output folders (harness.json)")
    p.add_argument("--all", action="store_true", help="every case, not only the misses")
    p.add_argument("--diff", nargs=2, metavar=("BEFORE", "AFTER"),
                   help="instead: the cases whose verdict differs between two harness runs of the same seed")
    a = p.parse_args(argv)
    if a.diff:
        r0, r1 = (json.loads((Path(d) / "harness.json").read_text()) for d in a.diff)
        before = {c["case"]: c for c in r0["cases"]}
        n = 0
        for c in r1["cases"]:
            b = before.get(c["case"])
            if b is not None and b["verdict"] != c["verdict"]:
                n += 1
                print(f"case {c['case']} {c['session']}: truth {c['truth']}: {b['verdict']} → {c['verdict']}")
        print(f"{n} verdicts changed of {len(r1['cases'])}; top-1 {r0['top1']:.3f} → {r1['top1']:.3f}, clean flagged "
              f"{r0['clean_flagged']} → {r1['clean_flagged']}")
        return 0
    print("| run | case | host | truth (params) | verdict | top-3 effects (A2, log score, worst fold, size/thr, "
          "S/s significant, R/r relevant) | the true effect: this case / the clean host |")
    print("|---|---|---|---|---|---|---|")
    for d in a.dirs:
        rep = json.loads((Path(d) / "harness.json").read_text())
        clean = {c["host"]: c for c in rep["cases"] if c["truth"] == "none"}
        for c in rep["cases"]:
            if c["correct"] and not a.all:
                continue
            top = "<br>".join(effect_line(s) for s in (c.get("scores") or [])[:3])
            mine = next((s for s in c.get("scores") or [] if s["name"] == c["truth"]), None)
            host = next((s for s in (clean.get(c["host"]) or {}).get("scores") or [] if s["name"] == c["truth"]),
                        None)
            both = " / ".join(effect_line(s) if s else "–" for s in (mine, host)) if c["truth"] != "none" else ""
            print(f"| {Path(d).name} | {c['case']} | {c['host'][:8]} | {c['truth']} ({_params(c.get('truth_params'))}) "
                  f"| {c['verdict']} | {top} | {both} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
