"""Benchmark: blind diagnosis of every body-worn single-sensor recording in ../shared/data (issue 5, S20-W).

One line per sensor: the verdict, the verdict physics expects (stated below BEFORE any verdict was looked at),
whether it is allowed, the top-3 ranking (penalised (A2), log score (A4) in nats per sample, size/threshold)
and time_offset's fit (channel, τ in samples, significant/relevant) — the effect found on the walking foot.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/w20_body_worn.py --out bench_out/w20/default
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/w20_body_worn.py --shift-prediction --out bench_out/w20/t13

Expected verdicts, from physics (walking, sensors strapped to the segments):
  feet, shanks → linear_acceleration: heel strike, push-off and swing put several m/s² RMS of linear
      acceleration on a foot (impacts of 2–5 g) and on a shank (a 0.3–0.4 m lever arm from the knee swinging at
      5–8 rad/s), above relevance (0.3 g … g, (L2)).
  thighs → none or linear_acceleration: the thigh turns slower (2–4 rad/s) about the hip at ~0.2 m, its
      sensor's linear acceleration (1–3 m/s² RMS plus the pelvis' own) lies near the 0.3 g relevance.
  pelvis → none or linear_acceleration: walking moves the pelvis by 1–2.5 m/s² RMS, below 0.3 g = 2.94 m/s².
Nothing else — no delay, vibration, magnet or drift — is known to be in these recordings; the x-IMU3 set streamed
over UDP (dropouts; timestamps from the device), so timestamp_jitter would need evidence beyond that.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

GAIT = {"Pelvis": "00B40B91", "L_UpLeg": "00B40C45", "R_UpLeg": "00B40C3C", "L_LowLeg": "00B40C44",
        "R_LowLeg": "00B40C47", "L_Foot": "00B40C55", "R_Foot": "00B40C48"}      # ../shared/data/README.md
XIO = {"pelvis": "pelvis 64F0EDBF (UDP)", "L_UpLeg": "Left Upper Leg 64F61CC4 (UDP)",
       "R_UpLeg": "Right Upper Leg 64F61C2E (UDP)", "L_LowLeg": "Left Lower Leg 64F61CB3 (UDP)",
       "R_LowLeg": "Right Lower Leg 64F61B2A (UDP)", "L_Foot": "Left Foot 64F0EBCE (UDP)",
       "R_Foot": "Right Foot 64F619FB (UDP)"}
LA = "linear_acceleration"


def expected(segment: str) -> tuple[str, ...]:
    """The verdicts physics allows for a walking segment (module doc)."""
    s = segment.lower()
    if "foot" in s or "lowleg" in s:
        return (LA,)
    return ("none", LA)


def sensors(data: Path) -> list[tuple[str, str, Path]]:
    """(set, segment, path) of every body-worn single sensor: gaittoolbox rawimu, then xio_lower_body."""
    out = [("gait", seg, data / "gaittoolbox" / "rawimu" / f"S02-Trial-Walk-1-000_{sid}.txt")
           for seg, sid in GAIT.items()]
    out += [("xio", seg, data / "xio_lower_body" / folder) for seg, folder in XIO.items()]
    return [x for x in out if x[2].exists()]


def jerk_lag(s, max_lag: int = 15) -> int:
    """Lag (samples, + = acc after gyr) maximising the correlation of the standardised jerk norms |Δacc|, |Δgyr|:
    impacts and turns seen by both channels peak together unless one channel is late."""
    import numpy as np

    a = np.linalg.norm(np.diff(s.acc, axis=0), axis=1)
    g = np.linalg.norm(np.diff(s.gyr, axis=0), axis=1)
    ok = np.isfinite(a) & np.isfinite(g)
    a, g = np.where(ok, (a - a[ok].mean()) / a[ok].std(), 0.0), np.where(ok, (g - g[ok].mean()) / g[ok].std(), 0.0)
    xc = [np.mean(a[max(0, k):len(a) + min(0, k)] * g[max(0, -k):len(g) + min(0, -k)])
          for k in range(-max_lag, max_lag + 1)]
    return int(np.argmax(xc)) - max_lag


def _fmt(r) -> str:
    s = r.size or {}
    return (f"{r.name}/{r.channel} pen {r.penalised:+.2f} ll {r.loglik_gain:+.3f} size "
            f"{s.get('value', float('nan')):.3g}/{s.get('threshold', float('nan')):.3g}"
            f"{' S' if r.significant else ''}{' R' if r.relevant else ''}{' X' if r.explained_by else ''}")


def main(argv=None) -> int:
    from imugraph.config import data_dir
    from imugraph.diagnose.bench import diagnose_options, model_arguments
    from imugraph.diagnose.run import diagnose
    from imugraph.io.readers import load_session
    from imugraph.io.writers import atomic_write_text, json_ready

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", default=None, help="comma-separated set:segment names (e.g. gait:L_Foot)")
    p.add_argument("--out", default="bench_out/w20", help="folder for body_worn.json")
    p.add_argument("--broad", default=None, help="instead: these BROAD trials (e.g. 04), same columns")
    model_arguments(p)
    args = p.parse_args(argv)
    opt = diagnose_options(args)
    only = set(args.only.split(",")) if args.only else None
    rows = []
    todo = sensors(Path(data_dir()))
    if args.broad:
        from imugraph.config import broad_dir
        todo = [("broad", tr, sorted(Path(broad_dir()).glob(f"{tr}_*.mat"))[0]) for tr in args.broad.split(",")]
    for kind, seg, path in todo:
        if only and f"{kind}:{seg}" not in only:
            continue
        s = load_session(path)
        c0 = time.process_time()
        d = diagnose(s, opt)
        cpu = time.process_time() - c0
        to = next((r for r in d.effects if r.name == "time_offset"), None)
        exp = expected(seg)
        row = {"set": kind, "segment": seg, "path": str(path), "verdict": d.verdict, "expected": list(exp),
               "ok": d.verdict in exp, "cpu_s": cpu, "rate_hz": float(s.rate), "duration_s": float(s.t[-1] - s.t[0]),
               "top3": [_fmt(r) for r in d.effects[:3]],
               "time_offset": None if to is None else {"channel": to.channel, "tau_samples": (to.size or {}).get("value"),
                                                       "threshold": (to.size or {}).get("threshold"),
                                                       "loglik_gain": to.loglik_gain, "significant": to.significant,
                                                       "relevant": to.relevant, "explained_by": to.explained_by},
               "verdict_result": next((_fmt(r) for r in d.effects if r.name == d.verdict), None)}
        rows.append(row)
        tol = (f"time_offset {to.channel} τ {(to.size or {}).get('value', float('nan')):.2f} smp ll "
               f"{to.loglik_gain:+.3f}{' S' if to.significant else ''}{' R' if to.relevant else ''}{' X' if to.explained_by else ''}"
               f" thr {(to.size or {}).get('threshold', float('nan')):.2f} folds τ "
               f"{','.join(f'{x:.2f}' for x in (to.fold_sizes or []))} ll "
               f"{','.join(f'{x:+.3f}' for x in (to.loglik_folds or []))}") if to else ""
        row["jerk_lag"] = jerk_lag(s)
        tol += f" | jerk lag acc−gyr {row['jerk_lag']:+d} smp"
        print(f"{kind}:{seg:9s} {d.verdict:20s} expect {'/'.join(exp):25s} {'yes' if row['ok'] else 'NO '} | "
              f"verdict {row['verdict_result'] or '-'} | top3: {'; '.join(row['top3'])} | {tol} | "
              f"{cpu:.1f} s CPU, {row['duration_s']:.0f} s at {s.rate:.0f} Hz", flush=True)
    n_ok = sum(r["ok"] for r in rows)
    print(f"verdict allowed by physics: {n_ok}/{len(rows)}; CPU {sum(r['cpu_s'] for r in rows):.0f} s")
    atomic_write_text(Path(args.out) / "body_worn.json", json.dumps(json_ready(rows), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
