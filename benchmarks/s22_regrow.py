"""Issue 3, helper S22: a stream started from a capped (30 s) bootstrap, with and without the bootstrap regrow.

Per BROAD trial: one capped bootstrap (`stream_run.bootstrap_calibration(max_s=…)`: at the cap calibrate's weak
fallback, D = s·I, o = 0 when the window holds too little rotation), then `stream_session` with
`bootstrap_regrow` = each of --modes (off: the start kept, as before; identified / weak: `stream_run.push_regrow`;
MODE+centre: with bootstrap_weak_centre, a weak start / window at its weak prior's centre, `stream_run.weak_centre`;
MODE+align: regrow_align, no heading jump at a switch, push_regrow eq. R2; helper S23: MODE+confirm: regrow_confirm =
--confirm, growth goes on after an identified switch, stream_regrow.regrow_consistent eq. C1; MODE+gF: this mode's
growth factor F instead of --grow; mode `default`: the uncapped bootstrap, grown until it identifies, no regrow —
the stream's default),
fixed lag (chain) 2 s, online θ-state calibration (the StreamOptions defaults). Online VQF on the same samples.

Reported per run: the filtered (causal) error over all movement samples and after the bootstrap window, the
smoothed error (imugraph.evaluate.orientation_error: best heading offset and time shift over the scored samples),
and, per segment of the filtered output between the regrow's switches, the RMS error at that global alignment
(`seg_global_deg`) and with the segment's own best heading offset (`seg_own_deg`): how much of the filtered error
is the heading jump at a switch. The regrow log (windows tried, switch times, CPU s of each calibrate + replay).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/s22_regrow.py 06,10,16 [--max-s 30] [--modes off,identified,weak]
        [--lag 2] [--grow 1.5] [--confirm 2] [--latency S] [--cache DIR] [--out s22_regrow.json]
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial, print_table, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.peers import vqf_online  # noqa: E402


def _score(q, s, mask):
    from imugraph.evaluate import orientation_error
    return orientation_error(q, s.quat, mask, s.rate).rms_deg if mask.any() else None


def _segments(q, s, mask, cuts):
    """Per segment [cut_j, cut_{j+1}) of the scored samples: RMS at the global alignment, and with its own."""
    from imugraph.evaluate import orientation_error, orientation_error_series
    idx, ang = orientation_error_series(q, s.quat, mask)
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        sel = (idx >= a) & (idx < b)
        m = mask & (np.arange(s.n) >= a) & (np.arange(s.n) < b)
        out.append({"from_s": float(s.t[a] - s.t[0]), "to_s": float(s.t[b - 1] - s.t[0]),
                    "seg_global_deg": float(np.sqrt(np.mean(ang[sel] ** 2))) if sel.any() else None,
                    "seg_own_deg": orientation_error(q, s.quat, m, s.rate).rms_deg if m.sum() > 100 else None})
    return out


def _mode(mode: str, grow: float, confirm: float) -> dict:
    """A --modes entry as stream_session's regrow keywords: BASE[+centre][+align][+confirm][+gF]."""
    parts = mode.split("+")
    g = [float(x[1:]) for x in parts if x.startswith("g") and x[1:].replace(".", "").isdigit()]
    return {"bootstrap_regrow": {"off": False, "identified": True, "weak": "weak", "default": False}[parts[0]],
            "bootstrap_weak_centre": "centre" in parts, "regrow_align": "align" in parts,
            "regrow_grow": g[0] if g else grow, "regrow_confirm": confirm if "confirm" in parts else None}


def run(path: Path, max_s: float, modes: list, lag: float, cache: str | None, grow: float = 1.5,
        latency: float | None = None, confirm: float = 2.0) -> list[dict]:
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import bootstrap_calibration, rest_gyro_bias, stream_session

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    pk = Path(cache) / f"s22_boot_{name}_max{max_s:g}.pkl" if cache else None
    if pk is not None and pk.exists():
        cal, n_boot = pickle.loads(pk.read_bytes())
    else:
        cal, n_boot = bootstrap_calibration(s, 30.0, max_s=max_s)
        if pk is not None:
            pk.write_bytes(pickle.dumps((cal, n_boot)))
    full = None
    if "default" in modes:                   # the uncapped bootstrap (the stream's default), cached apart
        pf = Path(cache) / f"s22_boot_{name}_full.pkl" if cache else None
        if pf is not None and pf.exists():
            full = pickle.loads(pf.read_bytes())
        else:
            full = bootstrap_calibration(s, 30.0)
            if pf is not None:
                pf.write_bytes(pickle.dumps(full))
    move = np.asarray(s.movement, bool)
    b_rest = rest_gyro_bias(s)
    after = move & (np.arange(s.n) >= n_boot)
    rows = []
    for mode in modes:
        kw = _mode(mode, grow, confirm)
        cpu0 = time.process_time()
        r = stream_session(s, None, StreamOptions(lag_s=lag), 30.0, bootstrap=full if mode == "default" else (cal, n_boot),
                           regrow_latency_s=latency, **kw)
        cpu = time.process_time() - cpu0
        log = r.timing.get("regrow") or []
        sw = [int(np.searchsorted(s.t, s.t[0] + e["switched_t"])) for e in log if e.get("switched_t") is not None]
        cuts = [0, n_boot] + [i for i in sw if i > n_boot] + [s.n]
        rows.append({"trial": name, "method": f"stream regrow {mode}", "filtered_deg": _score(r.filtered, s, move),
                     "filtered_after_deg": _score(r.filtered, s, after), "smoothed_deg": _score(r.smoothed, s, move),
                     "switches": len(sw), "last_switch_s": log[-1]["switched_t"] if sw else None,
                     "identified": bool(any(e.get("identified") and e.get("switched_t") is not None for e in log)),
                     "regrow_cpu_s": float(sum(e["cpu_s"] for e in log)), "cpu_s": cpu, "regrow": log,
                     "last_cut": cuts[-2], "filtered_final_deg": _score(r.filtered, s, move & (np.arange(s.n) >= cuts[-2])),
                     "segments": _segments(r.filtered, s, move, cuts), "start_identifiable":
                     bool((cal.coverage or {}).get("identifiable", True)), "bootstrap_span_s": float(s.t[n_boot - 1] - s.t[0]),
                     "start_D": r.start_calibration.D.tolist(), "start_o": r.start_calibration.o.tolist(),
                     "start_gyro_bias": r.start_calibration.gyro_bias.tolist(), "p99_cpu_ms": r.timing.get("p99_cpu_ms"),
                     "p99_between_cpu_ms": r.timing.get("p99_between_cpu_ms"), "updates": r.timing["updates"],
                     "cpu_realtime_factor": r.timing.get("cpu_realtime_factor"),
                     "n_boot": full[1] if mode == "default" else n_boot,
                     "filtered_after_own_deg": _score(r.filtered, s, move & (np.arange(s.n) >= (full[1] if mode == "default" else n_boot))),
                     "rest_gyro_bias": None if b_rest is None else b_rest.tolist()})
    q = vqf_online(s)
    rows.append({"trial": name, "method": "online VQF", "filtered_deg": _score(q, s, move),
                 "filtered_after_deg": _score(q, s, after)})
    for r in rows[:-1]:                  # VQF on each run's samples after its last switch (`filtered_final_deg`)
        r["vqf_final_deg"] = _score(q, s, move & (np.arange(s.n) >= r["last_cut"]))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="06,10,16")
    ap.add_argument("--max-s", type=float, default=30.0, help="the bootstrap's cap, s")
    ap.add_argument("--modes", default="off,identified,weak")
    ap.add_argument("--lag", type=float, default=2.0)
    ap.add_argument("--grow", type=float, default=1.5, help="the regrow's window growth factor (stream_session regrow_grow)")
    ap.add_argument("--confirm", type=float, default=2.0, help="regrow_confirm of the MODE+confirm modes (helper S23)")
    ap.add_argument("--latency", type=float, default=None, metavar="S",
                    help="fixed switch latency in s instead of the measured CPU time (regrow_latency_s): repeatable runs")
    ap.add_argument("--cache", default=None, help="DIR: keep / reuse each trial's capped bootstrap")
    ap.add_argument("--out", default="s22_regrow.json")
    a = ap.parse_args(argv)
    wanted = None if a.trials == "all" else {int(x) for x in a.trials.split(",")}
    modes = a.modes.split(",")
    rows = []
    for p in broad_trials():
        if wanted is None or trial_number(p) in wanted:
            rows += run(p, a.max_s, modes, a.lag, a.cache, a.grow, a.latency, a.confirm)
            print(f"trial {trial_number(p):02d} done", file=sys.stderr, flush=True)
    print_table(rows, ["trial", "method", "filtered_deg", "filtered_after_deg", "filtered_final_deg", "vqf_final_deg",
                       "smoothed_deg", "switches",
                       "last_switch_s", "identified", "regrow_cpu_s", "cpu_s"])
    for r in rows:
        if "start_D" in r:
            print(r["trial"], r["method"], "start D diag", np.round(np.diag(r["start_D"]), 2), "o", np.round(r["start_o"], 2),
                  "gyro bias", np.round(r["start_gyro_bias"], 4), "rest", r["rest_gyro_bias"] and np.round(r["rest_gyro_bias"], 4),
                  "switched to", [(round(e["span_s"], 1), np.round(np.diag(e["D"]), 2).tolist(), np.round(e["o"], 2).tolist())
                                  for e in r["regrow"] if "D" in e])
        for g in r.get("segments", []):
            print(r["trial"], r["method"], {k: (round(v, 2) if isinstance(v, float) else v) for k, v in g.items()})
    means = []
    for m in [f"stream regrow {x}" for x in modes] + ["online VQF"]:
        sel = [r for r in rows if r["method"] == m]
        mean = lambda k: float(np.mean([r[k] for r in sel if r.get(k) is not None])) if sel else None  # noqa: E731
        means.append({"method": m, "trials": len(sel), "filtered_deg": mean("filtered_deg"),
                      "filtered_after_deg": mean("filtered_after_deg"), "smoothed_deg": mean("smoothed_deg"),
                      "filtered_final_deg": mean("filtered_final_deg"), "vqf_final_deg": mean("vqf_final_deg"),
                      "filtered_after_own_deg": mean("filtered_after_own_deg"),
                      "p99_cpu_ms_max": max((r["p99_cpu_ms"] for r in sel if r.get("p99_cpu_ms") is not None), default=None),
                      "cpu_rt_min": min((r["cpu_realtime_factor"] for r in sel if r.get("cpu_realtime_factor")), default=None),
                      "cpu_rt_mean": mean("cpu_realtime_factor") if sel and "cpu_realtime_factor" in sel[0] else None,
                      "better_than_vqf": sum(r["filtered_deg"] < v["filtered_deg"] for r in sel for v in rows
                                             if v["method"] == "online VQF" and v["trial"] == r["trial"])})
    print_table(means, ["method", "trials", "filtered_deg", "filtered_after_deg", "smoothed_deg", "filtered_final_deg",
                        "vqf_final_deg", "filtered_after_own_deg", "p99_cpu_ms_max", "cpu_rt_min", "cpu_rt_mean",
                        "better_than_vqf"])
    write_json(a.out, {"rows": rows, "means": means, "max_s": a.max_s, "lag_s": a.lag, "grow": a.grow, "confirm": a.confirm,
                       "latency": a.latency,
                       "command": " ".join(sys.argv)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
