"""How robust are the disturbance-window verdicts of Options.window_trial_verdict to its two gates?

calibration/disturbance.py fit_offsets_on_trial: a window goes on trial when its offset leaves ≤ TRIAL_GAIN × its
RMS (first fit, orientations solved without it), and is kept modelled when its residual scale after the trial
solve is ≤ EXPLAINED × the undisturbed samples' scale of that same solve. This runs the calibration of each
BROAD trial with window_trial_verdict=True and the gates given, and prints per trial one JSON line: every
window's ratios at each judgement (gain = RMS after / before at the first fit; trial = scale / undisturbed
scale), its final verdict and left-out rows, the RMS orientation error (broad_published.py's score), the rounds
and the CPU time.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/b_window_gates.py [TRIALS] [--gain 0.5] [--explained 3.0]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import imugraph.calibration.disturbance as dist  # noqa: E402
import imugraph.calibration.rounds as rounds  # noqa: E402
from benchmarks.common import iter_broad  # noqa: E402
from imugraph.calibration.ml import Options, calibrate  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402


def _instrument(log: list) -> None:
    """Record the two ratios fit_offsets_on_trial compares with its gates (no change to what it computes)."""
    refit, solve_scale = dist._refit, rounds.undisturbed_rms

    def logged_refit(w, *a, **k):
        state = "decided" if w.decided else ("on_trial" if w.on_trial else "first")
        before = refit(w, *a, **k)
        if before is not None and state == "first":
            log.append({"t": round(float(a[0][w.start]), 1), "gain": round(w.residual_rms / before, 3)})
        elif before is not None and state == "on_trial":
            log.append({"t": round(float(a[0][w.start]), 1), "scale": w.residual_scale})
        return before

    def logged_scale(*a, **k):        # called once per round, right after the first on-trial window's refit
        ref = solve_scale(*a, **k)
        log.append({"ref": ref})
        return ref

    dist._refit, rounds.undisturbed_rms = logged_refit, logged_scale


def _ratios(log: list) -> list:
    """The log with each on-trial scale divided by its round's undisturbed scale: the ref marker right after it
    (the round's first on-trial window) or else the last one before it (later windows of the same round)."""
    out, ref = [], None
    for i, e in enumerate(log):
        if "ref" in e:
            ref = e["ref"]
        elif "scale" in e:
            nxt = log[i + 1]["ref"] if i + 1 < len(log) and "ref" in log[i + 1] else ref
            out.append({"t": e["t"], "trial": round(e["scale"] / nxt, 3)})
        else:
            out.append(e)
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", help="comma-separated trial numbers (default: all)")
    ap.add_argument("--gain", type=float, default=dist.TRIAL_GAIN, help="TRIAL_GAIN")
    ap.add_argument("--explained", type=float, default=dist.EXPLAINED, help="EXPLAINED")
    args = ap.parse_args(argv)
    dist.TRIAL_GAIN, dist.EXPLAINED = args.gain, args.explained
    log: list = []
    _instrument(log)
    select = set(args.trials.split(",")) if args.trials else None
    for _num, s, mask in iter_broad(select):
        log.clear()
        c0 = time.process_time()
        est = calibrate(s, Options(window_trial_verdict=True), allow_weak=True)
        cpu = time.process_time() - c0
        wins = [{"t": [round(w["t_start"], 1), round(w["t_end"], 1)], "modelled": w["modelled"],
                 "left_out_runs": len(w.get("left_out", []))} for w in est.calibration.disturbances]
        print(json.dumps({"trial": s.name[:2], "gain_gate": args.gain, "explained_gate": args.explained,
                          "rms_deg": round(orientation_error(est.quat, s.quat, mask, s.rate).rms_deg, 3),
                          "rounds": est.calibration.iterations, "converged": est.calibration.converged,
                          "cpu_s": round(cpu, 2), "windows": wins, "judgements": _ratios(log)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
