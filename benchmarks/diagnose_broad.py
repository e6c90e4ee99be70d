"""Benchmark: blind diagnosis of whole BROAD trials (no labels given), one line per trial.

Prints, per trial: the verdict, the winner's window (t_start–t_end, s), its held-out shrink, its fitted
size against the relevance threshold, the two next-ranked effects and the wall time; writes
broad_diagnosis.json under --out.

    .venv/bin/python benchmarks/diagnose_broad.py --trials 32,34,36,15,16,01,04,10
    .venv/bin/python benchmarks/diagnose_broad.py --trials all

Each line also names the verdicts the recording's own label allows (`expected_verdicts`: BROAD's trials.json
groups, read only to score, never by the diagnosis) and whether the verdict is one of them. The rule, from what
the experimenters did to each recording:
  attached / stationary magnet, office → magnetic_disturbance;  phone vibration → vibration;
  tapping (finger taps: short broadband shocks; the library has no impact effect) → vibration or none;
  undisturbed rotation → none;  undisturbed fast translation or combined motion → linear_acceleration;
  undisturbed slow translation or combined motion → none or linear_acceleration (the hand's slow linear
  acceleration may lie below the effect's relevance);  mixed → any effect but none.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.common import groups_of  # noqa: E402

DEFAULT = "32,34,36,15,16,01,04,10"
ALL = "01,02,04,06,07,10,12,15,16,21,24,26,28,30,32,34,36"
EFFECTS = ("magnetic_disturbance", "linear_acceleration", "gyro_bias_drift", "time_offset", "gyro_scale",
           "saturation", "accelerometer_bias", "vibration")


def expected_verdicts(groups: list[str]) -> tuple[str, ...]:
    """The verdicts a BROAD recording's label allows (module docstring), from its trials.json groups.

    Returns () when the groups say nothing (trials.json absent): the line then reports no match.
    """
    g = set(groups)
    if g & {"attached_magnet", "stationary_magnet", "office_environment"}:
        return ("magnetic_disturbance",)
    if "vibration" in g:
        return ("vibration",)
    if "tapping" in g:
        return ("vibration", "none")
    if "mixed" in g:
        return EFFECTS
    if "undisturbed" not in g:
        return ()
    if "rotation" in g:
        return ("none",)
    if "fast" in g:
        return ("linear_acceleration",)
    return ("none", "linear_acceleration")


def main(argv=None) -> int:
    from imugraph.config import broad_dir
    from imugraph.diagnose.bench import diagnose_options, model_arguments
    from imugraph.diagnose.run import best_result, diagnose
    from imugraph.io.readers import load_session
    from imugraph.io.writers import atomic_write_text, json_ready

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default=DEFAULT,
                   help=f"BROAD trial numbers, comma separated, or 'all' ({ALL}); default {DEFAULT}")
    p.add_argument("--keyframe-hz", type=float, default=5.0)
    p.add_argument("--out", default="bench_out/diagnose_broad", help="folder for broad_diagnosis.json")
    model_arguments(p)
    args = p.parse_args(argv)
    opt = diagnose_options(args, keyframe_hz=args.keyframe_hz)
    root = broad_dir()
    rows = []
    trials = ALL if args.trials == "all" else args.trials
    for tr in [t.strip() for t in trials.split(",") if t.strip()]:
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
        row["expected_verdicts"] = list(expected_verdicts(groups_of(hits[0], root)))
        row["label_match"] = d.verdict in row["expected_verdicts"]
        rows.append(row)
        w = f" window {win.t_start:.1f}–{win.t_end:.1f} s" if win and win.t_start is not None else ""
        nan = float("nan")
        sh = (f" shrink {win.shrink:.2f} size {size.get('value', nan):.3g}/{size.get('threshold', nan):.3g} "
              f"{size.get('unit', '')}") if win else ""
        nxt = ", ".join(f"{n} ({pen:+.2f}{' sig' if sg else ''}{' rel' if rl else ''})"
                        for n, pen, sg, rl in row["ranking"])
        exp = "/".join(row["expected_verdicts"]) or "?"
        print(f"{hits[0].stem}: {d.verdict}{w}{sh} | ranked: {nxt} | label allows {exp}: "
              f"{'yes' if row['label_match'] else 'NO'} | {sec:.0f} s for {row['duration_s']:.0f} s", flush=True)
    if rows:
        n_ok = sum(r["label_match"] for r in rows)
        print(f"verdict allowed by the recording's label: {n_ok}/{len(rows)}")
    out = Path(args.out)
    atomic_write_text(out / "broad_diagnosis.json", json.dumps(json_ready(rows), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
