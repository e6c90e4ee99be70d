"""Benchmark (V20, issue 5): vibration and time_offset on whole BROAD trials — the numbers behind the verdict.

Per trial: the verdict (window, held-out shrink), then the vibration effect's result — its windows, f₀ and
band, its size (band RMS of the excess) against the relevance threshold, and, with the motion check (V6), the
band RMS the measured angular motion explains at a hand's lever arm (`motion_rms`) — and the time_offset
result (channel, τ in samples, τ fitted on each fold's training samples and, with the timing confidence (T12),
its jackknife SE in the size), significant / relevant flags.

--skew (no diagnosis): per trial the accelerometer's delay against the gyro from time_offset's own fit with
the channel held at acc (T1)/(T2), on all samples, on the slower / faster half of the moving samples (0.5 s
moving mean of |y_gyr| above / below its median over the samples turning faster than 0.3 rad/s), and
without the impulsive rows (50 ms moving mean of the above-15-Hz accelerometer residual power > 10 × its
median: taps, knocks), plus the share of the all-sample fit's training-cost reduction in those rows.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/v20_vibration_check.py --trials 06,07,24,26 \
        [--vibration-motion-check] [--timing-confidence] --out DIR
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/v20_vibration_check.py --skew --trials 01,02,04,06,07,24,26
    .venv/bin/python benchmarks/v20_vibration_check.py --harness DIR [DIR ...]

--harness (no diagnosis): from harness.json files (benchmarks/diagnose_harness.py), per case whose truth or
verdict is vibration or time_offset, or whose vibration / time_offset result is significant: the truth, the
verdict and those two effects' size / threshold (with the options: the raised thresholds (V6') / (T12)).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

DEFAULT = "06,07,24,26"


def _fmt(x, spec=".3f"):
    try:
        return format(float(x), spec)
    except (TypeError, ValueError):
        return "–"


def effect_line(r) -> str:
    """One effect's numbers: flags, size/threshold (and the size dict's extra numbers), log score and folds."""
    s = dict(r.size or {})
    extra = " ".join(f"{k} {_fmt(v)}" for k, v in s.items() if k not in ("value", "threshold", "unit")
                     and isinstance(v, (int, float)))
    folds = " ".join(_fmt(f, "+.3f") for f in (r.loglik_folds or []))
    return (f"{r.name} [{r.stage}] ch {r.channel} sig {int(bool(r.significant))} rel {int(bool(r.relevant))} "
            f"size {_fmt(s.get('value'))}/{_fmt(s.get('threshold'))} {s.get('unit', '')} {extra} | "
            f"logscore {_fmt(r.loglik_gain, '+.4f')} folds [{folds}] | shrink {_fmt(r.shrink, '.2f')} "
            f"gap {_fmt(r.gap_before)}→{_fmt(r.gap_after)}")


def skew(session) -> str:
    """--skew: the accelerometer's delay against the gyro (time_offset's fit, channel held at acc), in samples,
    on all / slow / fast / non-impulsive rows, and the impulsive rows' share of the cost reduction."""
    import numpy as np

    from imugraph.diagnose.effects.base import smooth
    from imugraph.diagnose.effects.time_offset import EFFECT as TIME_OFFSET
    from imugraph.diagnose.effects.vibration import above_motion_band
    from imugraph.diagnose.fit import base_options, fit_base

    f = fit_base(session, base_options(5.0))
    rate = session.rate
    w = smooth(np.linalg.norm(session.gyr, axis=1), int(round(0.5 * rate)))
    moving = w > 0.3
    med = float(np.median(w[moving]))
    e = smooth(np.sum(above_motion_band(f.residuals["acc"], rate) ** 2, axis=1), int(round(0.05 * rate)))
    imp = e > 10.0 * float(np.nanmedian(e))
    parts = {"all": np.ones(f.n, bool), "slow": moving & (w < med), "fast": moving & (w >= med), "no-impulse": ~imp}
    taus = {k: TIME_OFFSET.fit(f, m, candidates=("acc",)).params["tau_s"] * rate for k, m in parts.items()}
    c = TIME_OFFSET.fit(f, parts["all"], candidates=("acc",))
    sg = np.asarray(f.sigma["acc"], float)
    d = np.nansum((f.residuals["acc"] / sg) ** 2, 1) - np.nansum((c.raw_residuals(f)["acc"] / sg) ** 2, 1)
    share = float(np.nansum(d[imp]) / np.nansum(d))
    return (", ".join(f"{k} {v:+.2f}" for k, v in taus.items()) + f" samples | |ω| median in motion {med:.2f} rad/s"
            f" | impulsive rows {100 * imp.mean():.1f} %, their share of the acc cost reduction {share:.2f}")


def harness_table(dirs) -> None:
    """--harness: the vibration / time_offset numbers of the harness cases (module doc)."""
    for d in dirs:
        rep = json.loads((Path(d) / "harness.json").read_text())
        print(f"== {d}")
        for c in rep.get("cases", []):
            sc = {x["name"]: x for x in (c.get("scores") or []) if x["name"] in ("vibration", "time_offset")}
            if not ({c.get("truth"), c.get("verdict")} & {"vibration", "time_offset"}
                    or any(x.get("significant") for x in sc.values())):
                continue
            parts = [f"{n} {_fmt(x.get('size'))}/{_fmt(x.get('threshold'))} sig {int(bool(x.get('significant')))} "
                     f"rel {int(bool(x.get('relevant')))}" for n, x in sorted(sc.items())]
            print(f"  {c['case']} {c['session']}: truth {c['truth']} verdict {c['verdict']} | " + " | ".join(parts))


def main(argv=None) -> int:
    from imugraph.config import broad_dir
    from imugraph.diagnose.bench import diagnose_options, model_arguments
    from imugraph.diagnose.run import best_result, diagnose
    from imugraph.io.readers import load_session
    from imugraph.io.writers import atomic_write_text, json_ready

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default=DEFAULT, help=f"BROAD trial numbers, comma separated (default {DEFAULT})")
    p.add_argument("--out", default="bench_out/v20_vibration_check", help="folder for v20_check.json")
    p.add_argument("--skew", action="store_true", help="the accelerometer-vs-gyro delay only (no diagnosis)")
    p.add_argument("--harness", nargs="+", default=None, metavar="DIR", help="tabulate harness.json files only")
    model_arguments(p)
    args = p.parse_args(argv)
    if args.harness:
        harness_table(args.harness)
        return 0
    opt = diagnose_options(args)
    root = Path(broad_dir())
    rows = []
    for tr in [t.strip() for t in args.trials.split(",") if t.strip()]:
        hits = sorted(root.glob(f"{tr}_*.mat")) if root.is_dir() else []
        if not hits:
            print(f"{tr}: not found under {root}", file=sys.stderr)
            continue
        s = load_session(hits[0])
        if args.skew:
            print(f"{hits[0].stem}: acc delay (acc held) {skew(s)}", flush=True)
            continue
        t0 = time.process_time()
        d = diagnose(s, opt)
        cpu = time.process_time() - t0
        win = best_result(d)
        w = f" window {win.t_start:.1f}–{win.t_end:.1f} s" if win and win.t_start is not None else ""
        sh = f" shrink {win.shrink:.2f}" if win else ""
        print(f"{hits[0].stem}: verdict {d.verdict}{w}{sh} ({cpu:.0f} s CPU)", flush=True)
        row = {"trial": hits[0].stem, "verdict": d.verdict, "cpu_s": cpu, "effects": {}}
        for r in d.effects:
            if r.name in ("vibration", "time_offset") or r.name == d.verdict:
                prm = dict(r.params or {})
                if r.name == "vibration":
                    wins = [(round(x["t_start"], 1), round(x["t_end"], 1)) for x in prm.get("windows", [])]
                    print(f"   vibration windows {wins} f0 {_fmt(prm.get('freq_hz'), '.1f')} Hz band "
                          f"{[round(b, 1) for b in prm.get('band_hz', [])]} Hz")
                if r.name == "time_offset":
                    tau = float(prm.get("tau_s", float("nan"))) * s.rate
                    print(f"   time_offset channel {prm.get('channel')} τ {tau:+.2f} samples, |τ| per fold "
                          f"{[round(x, 2) for x in (r.fold_sizes or [])]}, train cost reduction "
                          f"{_fmt(prm.get('train_cost_reduction'), '.4f')}")
                print("   " + effect_line(r), flush=True)
                row["effects"][r.name] = r.as_dict()
        rows.append(row)
    out = Path(args.out)
    atomic_write_text(out / "v20_check.json", json.dumps(json_ready(rows), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
