"""Task K2 (issue 3): is the stream's bounded position (StreamOptions.position_sigma, stream_position K1–K3) safe
on a sensor that TRAVELS, and does the bootstrap's choice of σ_p (StreamOptions.position_select,
stream_run.select_position, calibration.position_select J2) keep it off there?

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/k3_travel.py walk [--seeds 1,2] \
        --variant "" --variant "position_sigma=0.3" --variant "position_sigma=1.0" \
        --variant "position_select=(1e4,1.0,0.3,0.1)"
    ... benchmarks/k3_travel.py gait [--segments Pelvis,LeftFoot] --variant ...
    ... benchmarks/k3_travel.py broad [--trials 01,02] [--cache DIR] --variant ...

Data:
- walk: benchmarks/j2_travel.travel_session(seed, "walk") — imugraph.sim's rotations (180 s, 100 Hz) with a
  ≈ 200 m wandering walk at 1.3 m/s; scored against the simulated truth over `movement`.
- gait: gaittoolbox S02-Trial-Walk-1, one MTw at a time (as benchmarks/j2_gait.py), 25 s; scored against the
  MTw's onboard orientation (Xsens' filter: a reference, not the truth) over the whole recording. The 30 s
  bootstrap grows to the whole recording here (a replay: the calibration saw every sample).
- broad: the BROAD trials, scored against opt_quat over `movement` (as stream_speed.py).

Stream set-up as `benchmarks/stream_speed.py --lag 2 --lag-solver chain --lag-only`: a 30 s bootstrap
(`bootstrap_calibration`), then `stream_session` with StreamOptions(lag_s=2, fixed_lag_solver="chain", variant).
A variant with position_select bootstraps itself with the selection (`select_position`); the others share the
default bootstrap. Printed per session and variant: filtered and smoothed RMS total (inclination, heading) error,
σ_p used, CPU real-time factor, p99 CPU per update. The estimator never sees the truth. Writes
bench_out/k3_travel_<kind>.json.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts  # noqa: E402
from benchmarks.k3_recovery import parse_variant  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from imugraph.graphs.stream import StreamOptions  # noqa: E402
from imugraph.graphs.stream_run import bootstrap_calibration, select_position, stream_session  # noqa: E402

BOOTSTRAP_S = 30.0


def sessions(kind: str, a) -> list:
    """[(name, session, scoring mask)] of the chosen data."""
    if kind == "walk":
        from benchmarks.j2_travel import travel_session
        out = []
        for seed in (int(x) for x in a.seeds.split(",")):
            s, p = travel_session(seed, "walk")
            out.append((f"walk{seed} ({np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)):.0f} m)", s, s.movement))
        return out
    if kind == "gait":
        from benchmarks.j2_gait import SEGMENTS
        from imugraph.config import data_dir
        from imugraph.io.gaittoolbox import read_gaittoolbox
        body = read_gaittoolbox(data_dir() / "gaittoolbox" / "rawimu", "S02-Trial-Walk-1")
        segs = a.segments.split(",") if a.segments else list(SEGMENTS)
        return [(seg, body.sensors[seg], np.ones(body.sensors[seg].n, bool)) for seg in segs]
    from benchmarks.common import broad_trials, load_broad_trial, trial_number
    from benchmarks.stream_arrival import trial_paths
    out = []
    for p in (broad_trials() if a.trials == "all" else trial_paths(a.trials)):
        s = load_broad_trial(p)
        out.append((f"{trial_number(p):02d}", s, s.movement))
    return out


def _boot(name: str, s, cache: str | None, select: tuple | None, base: StreamOptions, boot_s: float = BOOTSTRAP_S):
    """(cal, n_boot, options) of the default bootstrap (select None) or of select_position; cached per name
    (k2_boot_<name>.pkl / k2_sel_<name>.pkl) with --cache."""
    key = "".join(c for c in name.split(" ")[0] if c.isalnum())
    path = None if not cache else Path(cache) / f"k2_{'sel' if select else 'boot'}_{key}.pkl"
    if path is not None and path.exists():
        cal, n, sigma, dlogz = pickle.loads(path.read_bytes())
    elif select:
        info: dict = {}
        cal, n, o = select_position(s, StreamOptions(position_select=select), boot_s, info=info)
        sigma = o.position_sigma
        sel = next((h["position_select"] for h in info.get("history", []) if "position_select" in h), None)
        # ln Z(σ) − ln Z(off) per candidate (eq. J2), the selection's own scores
        off = [c["log_z"] for c in sel["scores"] if c["sigma_p"] >= 1e4] if sel else []
        dlogz = {f"{c['sigma_p']:g}": c["log_z"] - off[0] for c in sel["scores"]} if off else None
    else:
        cal, n = bootstrap_calibration(s, boot_s)
        sigma, dlogz = base.position_sigma, None
    if path is not None and not path.exists():
        path.write_bytes(pickle.dumps((cal, n, sigma, dlogz)))
    from dataclasses import replace
    return cal, n, (replace(base, position_sigma=sigma) if select else base), dlogz


def track_position(s, cal, n_boot: int, opts: StreamOptions) -> dict:
    """The stream's filtered keyframe position (StreamSmoother._p, the Pose3 translation: the integral of the
    filtered velocities, = the bounded p_k up to (K1)'s σ_kin when position_sigma is on) after every sample, from
    the first keyframe on: p95 and max of its horizontal distance from the start. Why: a causal travel check needs
    to know how far a bounded stream lets a walking sensor's position go against a hand-held one's."""
    from imugraph.graphs.stream_run import session_smoother
    sm = session_smoother(s, cal, n_boot, opts)
    ph = np.empty(s.n)
    rows = np.column_stack((s.t, s.gyr, s.acc, s.mag)).tolist()
    for i, row in enumerate(rows):
        sm.push_floats(*row)
        ph[i] = float(np.hypot(*np.asarray(sm._p, float)[:2]))
    return {"p95_m": float(np.percentile(ph, 95)), "max_m": float(ph.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", choices=("walk", "gait", "broad"))
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--segments", default=None)
    ap.add_argument("--trials", default="all")
    ap.add_argument("--cache", default=None, help="DIR: bootstraps stored per session (30 s ones only)")
    ap.add_argument("--bootstrap-s", type=float, default=BOOTSTRAP_S, help="bootstrap window (s), 30 as stream_speed")
    ap.add_argument("--track-p", action="store_true", help="also the filtered keyframe position's spread (a "
                    "second pass through session_smoother): p95 of |p̂_k| horizontal, in m and in σ_p")
    ap.add_argument("--variant", action="append", default=None, help='StreamOptions "k=v;k=v" ("": default)')
    a = ap.parse_args(argv)
    if a.bootstrap_s != BOOTSTRAP_S:
        a.cache = None
    variants = a.variant if a.variant is not None else [""]
    rows = []
    for name, s, mask in sessions(a.kind, a):
        for text in variants:
            kw = {"lag_s": 2.0, "fixed_lag_solver": "chain", **parse_variant(text)}
            select = kw.pop("position_select", None)
            c0 = time.process_time()
            cal, n_boot, opts, dlogz = _boot(name, s, a.cache, select, StreamOptions(**kw), a.bootstrap_s)
            boot_cpu = time.process_time() - c0
            r = stream_session(s, None, opts, a.bootstrap_s, bootstrap=(cal, n_boot))
            tm = r.timing
            row = {"session": name, "variant": text, "sigma_p": opts.position_sigma, "boot_cpu_s": boot_cpu,
                   "filtered": error_parts(r.filtered, s, mask), "smoothed": error_parts(r.smoothed, s, mask),
                   "cpu_rt": tm.get("cpu_realtime_factor"), "p99_cpu_ms": tm.get("p99_cpu_ms"),
                   "failed": r.counts["failed_updates"], "n_boot": n_boot, "samples": s.n, "dlogz_vs_off": dlogz}
            if a.track_p:
                row.update(track_position(s, cal, n_boot, opts))
            rows.append(row)
            f, m = row["filtered"], row["smoothed"]
            print(f"{name} [{text}] σp {opts.position_sigma}: filtered {f[0]:.2f} (i {f[1]:.2f} h {f[2]:.2f}) "
                  f"smoothed {m[0]:.2f} (i {m[1]:.2f} h {m[2]:.2f}) | {row['cpu_rt']:.0f}× RT, p99 "
                  f"{row['p99_cpu_ms']:.2f} ms CPU, failed {row['failed']}, boot {n_boot}/{s.n} rows "
                  f"({boot_cpu:.1f} s CPU)" + ("" if dlogz is None else " ln Z − ln Z(off): " + ", ".join(
                      f"{k} {v:+.1f}" for k, v in dlogz.items()))
                  + ("" if "p95_m" not in row else f" | p̂ horizontal p95 {row['p95_m']:.2f} m, max {row['max_m']:.2f} m"),
                  flush=True)
    for text in variants:
        sub = [r for r in rows if r["variant"] == text]
        print(f"[{text}] mean filtered {np.mean([r['filtered'][0] for r in sub]):.3f}° (incl "
              f"{np.mean([r['filtered'][1] for r in sub]):.3f}°) smoothed {np.mean([r['smoothed'][0] for r in sub]):.3f}° "
              f"(incl {np.mean([r['smoothed'][1] for r in sub]):.3f}°); min RT {min(r['cpu_rt'] for r in sub):.0f}×, "
              f"worst p99 {max(r['p99_cpu_ms'] for r in sub):.2f} ms; σp {[r['sigma_p'] for r in sub]}")
    write_json(f"k3_travel_{a.kind}.json", {"variants": variants, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
