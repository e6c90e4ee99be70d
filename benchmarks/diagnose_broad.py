"""Benchmark: blind diagnosis of whole BROAD trials (no labels given), one line per trial.

Prints, per trial: the verdict, the winner's window (t_start–t_end, s), its held-out shrink, its fitted
size against the relevance threshold, the two next-ranked effects and the wall time; writes
broad_diagnosis.json under --out.

    .venv/bin/python benchmarks/diagnose_broad.py --trials 32,34,36,15,16,01,04,10
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

DEFAULT = "32,34,36,15,16,01,04,10"


def main(argv=None) -> int:
    from imugraph.config import broad_dir
    from imugraph.diagnose.bench import diagnose_options, model_arguments
    from imugraph.diagnose.run import best_result, diagnose
    from imugraph.io.readers import load_session
    from imugraph.io.writers import atomic_write_text, json_ready

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default=DEFAULT, help=f"BROAD trial numbers, comma separated (default {DEFAULT})")
    p.add_argument("--keyframe-hz", type=float, default=5.0)
    p.add_argument("--out", default="bench_out/diagnose_broad", help="folder for broad_diagnosis.json")
    model_arguments(p)
    args = p.parse_args(argv)
    opt = diagnose_options(args, keyframe_hz=args.keyframe_hz)
    root = broad_dir()
    rows = []
    for tr in [t.strip() for t in args.trials.split(",") if t.strip()]:
        hits = sorted(Path(root).glob(f"{tr}_*.mat")) if Path(root).is_dir() else []
        if not hits:
            print(f"{tr}: not found under {root}", file=sys.stderr)
            continue
        s = load_session(hits[0])
        t0 = time.perf_counter()
        d = diagnose(s, opt)
        sec = time.perf_counter() - t0
        win = best_result(d)
        size = (win.size or {}) if win else {}
        row = {"trial": hits[0].stem, "verdict": d.verdict, "seconds": sec, "duration_s": float(s.t[-1] - s.t[0]),
               "t_start": win.t_start if win else None, "t_end": win.t_end if win else None,
               "shrink": win.shrink if win else None, "size": size,
               "ranking": [(r.name, round(float(r.penalised), 3), r.significant, r.relevant)
                           for r in d.effects[:3]]}
        rows.append(row)
        w = f" window {win.t_start:.1f}–{win.t_end:.1f} s" if win and win.t_start is not None else ""
        nan = float("nan")
        sh = (f" shrink {win.shrink:.2f} size {size.get('value', nan):.3g}/{size.get('threshold', nan):.3g} "
              f"{size.get('unit', '')}") if win else ""
        nxt = ", ".join(f"{n} ({pen:+.2f}{' sig' if sg else ''}{' rel' if rl else ''})"
                        for n, pen, sg, rl in row["ranking"])
        print(f"{hits[0].stem}: {d.verdict}{w}{sh} | ranked: {nxt} | {sec:.0f} s for {row['duration_s']:.0f} s",
              flush=True)
    out = Path(args.out)
    atomic_write_text(out / "broad_diagnosis.json", json.dumps(json_ready(rows), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
