"""Issue 3, incremental runs: BROAD trials streamed sample by sample, beside online VQF in the same run.

Per trial (read once, not timed):
    stream iSAM2 / stream lag   imugraph.graphs.stream_run.stream_session: bootstrap calibration on the
                                first --bootstrap-s seconds (batch ML; then re-estimated online, or held fixed: --calibration; its wall time is given
                                apart), then every sample pushed in order; iSAM2 over the whole trial, and
                                the fixed-lag smoother with --lag seconds
    batch smooth                imugraph.graphs.cpp_smoother.smooth_fixed with the same calibration: what
                                the smoothed stream should reproduce ("vs batch": RMS difference, no alignment)
    online VQF                  benchmarks.peers.vqf_online (VQF(Ts).updateBatch) on the published field
Reported: real-time factor (samples per second streamed ÷ sampling rate; the bootstrap not included),
per-update latency p50/p99 (ms; one update per keyframe), the same from CPU time (`cpu_rt`, `p99_cpu_ms`:
process / thread CPU, not inflated by other processes on a shared machine; `max_cpu_ms`), the periodic work done on
samples between keyframes (`p99_btw_cpu_ms`, `max_btw_cpu_ms`: the chain lag's marginalisation / relinearisation
and the online refits, StreamSmoother._between_keyframes), the largest entry of the bootstrap's gyro map E
(`E_max`; applied to the gyro), and the orientation error vs opt_quat over
`movement` (imugraph.evaluate.orientation_error: best heading offset and time shift) of the filtered
(causal) and smoothed outputs. The filtered rows of the bootstrap window are a replay with the bootstrap
calibration (see docs/stream.md). Wall times; the machine may be shared: compare ratios in one run.

    .venv/bin/python benchmarks/stream_speed.py [TRIALS] [--lag 2 | --no-lag] [--no-batch] [--bootstrap-s 30]
        [--calibration online|fixed|both] [--lag-solver chain|incremental|batch] [--lag-only] [--no-cal-compare] [--[no-]calib-states]
        [--[no-]disturb] [--weak-prior] [--[no-]offsets] [--cache DIR] [--opt KEY=VALUE ...]   (defaults: StreamOptions')
        [--bootstrap-max-s S] [--score-after-bootstrap]   (the bootstrap's growth capped; the filtered error and online
        VQF's also on the movement samples after each trial's bootstrap window only: `filtered_after_deg`)
        [--bootstrap-regrow off|identified|weak] [--bootstrap-weak-centre]   (a capped start's bootstrap keeps growing
        while streaming; a weak start at its prior's centre: S22)
        [--regrow-align] [--regrow-grow F] [--regrow-confirm C] [--regrow-latency S]   (helper S23: stream_session's
        regrow_align / regrow_grow / regrow_confirm / regrow_latency_s; `imugraph stream --bootstrap-regrow` is
        --bootstrap-max-s 30 --bootstrap-regrow weak --bootstrap-weak-centre --regrow-align --regrow-grow 1.2
        --regrow-confirm 2)

TRIALS: comma-separated BROAD trial numbers, or "all" (the 17 trials; default 01). --no-lag / --no-batch skip
the fixed-lag run / the batch smoother (time). Prints the per-trial table, then the means of the filtered
error of every streamed method beside online VQF's over the same trials. Writes bench_out/stream_speed.json (--out NAME).
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial, peak_memory_mb, print_table, stream_overrides, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.peers import timed, vqf_online  # noqa: E402
from imugraph.io.writers import atomic_write_bytes  # noqa: E402


def _err(q, s):
    from imugraph.evaluate import orientation_error
    return orientation_error(q, s.quat, s.movement, s.rate).rms_deg


def _err_after(q, s, n_boot: int):
    """--score-after-bootstrap: the error over the movement samples after the bootstrap's window (its last row
    n_boot − 1), where the filtered output is causal; None when the bootstrap took the whole trial."""
    from imugraph.evaluate import orientation_error
    if n_boot >= s.n:
        return None
    mask = np.asarray(s.movement, bool) & (np.arange(s.n) >= n_boot)
    return orientation_error(q, s.quat, mask, s.rate).rms_deg if mask.any() else None


def run_trial(path: Path, lag: float | None, bootstrap_s: float, batch: bool = True, online=(True,),
              compare_cal: bool = True, lag_solver: str = "chain", lag_only: bool = False, calib_states: bool = True,
              disturb: bool = True, weak_prior: bool = False, cache: str | None = None, offsets: bool = True,
              extra: dict | None = None, bootstrap_max_s: float | None = None, after: bool = False,
              regrow: bool | str = False, weak_centre: bool = False, regrow_kw: dict | None = None) -> list[dict]:
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import bootstrap_calibration, stream_session

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    solvers = ([] if lag_only else [("stream iSAM2", None)]) + ([(f"stream lag {lag:g} s", lag)] if lag is not None else [])
    runs = [(f"{label} {'online' if on else 'fixed'} cal", lag_s, on) for label, lag_s in solvers for on in online]
    want_full = compare_cal and any(on for *_, on in runs)
    tag = name if bootstrap_max_s is None else f"{name}_max{bootstrap_max_s:g}"      # a capped bootstrap apart
    cached = _cache_load(cache, tag)
    if cached is not None:
        cal, n_boot, boot = cached["boot"], cached["n_boot"], cached["boot_seconds"]
        dirty = False
    else:
        start = time.perf_counter()
        cal, n_boot = bootstrap_calibration(s, bootstrap_s, max_s=bootstrap_max_s)
        boot = time.perf_counter() - start
        cached, dirty = {"boot": cal, "n_boot": n_boot, "boot_seconds": boot}, True
    q_batch, t_batch = timed(smooth_fixed, s, cal) if batch else (None, None)
    rows = []
    cal_full, f_batch = cached.get("full"), cached.get("f_batch")
    if want_full and cal_full is None:
        from imugraph.calibration.ml import Options, calibrate
        from imugraph.errors import CalibrationError
        same_model = Options()          # the batch default (gyro map E on), as the bootstrap; the stream applies
        #                                 the bootstrap's E and re-estimates D, o only
        try:
            est_full = calibrate(s, same_model)            # the batch calibration of the whole trial
        except CalibrationError:                           # too little rotation (10, 12, 15, 16): regularised
            est_full = calibrate(s, same_model, allow_weak=True)
        cal_full = est_full.calibration
        f_batch = _whiteness(est_full.residuals.get("mag"), s.t)
        cached.update(full=cal_full, f_batch=f_batch)
        dirty = True
    if dirty and cache:
        atomic_write_bytes(Path(cache) / f"cal_{tag}.pkl", pickle.dumps(cached))
    for label, lag_s, on in runs:
        opts = StreamOptions(lag_s=lag_s, online_calibration=on, fixed_lag_solver=lag_solver, calib_states=calib_states,
                             disturb_detect=disturb, calib_weak_prior=weak_prior, disturb_offsets=offsets, **(extra or {}))
        # the bootstrap computed above (not timed again); stream_session then learns the detector's σ_f over its
        # window and takes the weak prior's s from it, as when it bootstraps itself
        r = stream_session(s, None, opts, bootstrap_s, bootstrap=(cal, n_boot), bootstrap_regrow=regrow,
                           bootstrap_weak_centre=weak_centre, **(regrow_kw or {}))
        log = r.timing.get("regrow") or []
        sw = [e for e in log if e.get("switched_t") is not None]
        tm = r.timing
        rows.append({"trial": name, "method": label, "rt_factor": tm["realtime_factor"], "p50_ms": tm["p50_ms"],
                     "p99_ms": tm["p99_ms"], "cpu_rt": tm.get("cpu_realtime_factor"), "p99_cpu_ms": tm.get("p99_cpu_ms"),
                     "max_cpu_ms": tm.get("max_cpu_ms"), "p99_btw_cpu_ms": tm.get("p99_between_cpu_ms"),
                     "max_btw_cpu_ms": tm.get("max_between_cpu_ms"), "E_max": float(np.abs(cal.gyro_map).max()),
                     "filtered_deg": _err(r.filtered, s), "smoothed_deg": _err(r.smoothed, s),
                     **({"filtered_after_deg": _err_after(r.filtered, s, n_boot)} if after else {}),
                     "vs_batch_deg": orientation_error(r.smoothed, q_batch, None, s.rate, heading=False,
                                                       max_shift=0.0).rms_deg if batch else None,
                     "seconds": tm["seconds"], "bootstrap_s": boot, "failed": r.counts["failed_updates"],
                     **({"regrow_windows": len(log), "regrow_switches": len(sw),
                         "regrow_last_switch_s": sw[-1]["switched_t"] if sw else None,
                         "regrow_identified": any(e.get("identified") and e.get("switched_t") is not None for e in log),
                         "regrow_cpu_s": float(sum(e["cpu_s"] for e in log))} if regrow else {}),
                     "dist": r.counts.get("disturbances"), "dist_kf": r.counts.get("disturbed_keyframes"),
                     **(_cal_agreement(r.calibration, cal_full) if on and cal_full is not None else {}),
                     **(_last_refit(r.calibration_history, r.calibration, cal_full, f_batch) if on and cal_full is not None else {}),
                     **(_white_z(r.calibration_history, r.calibration, cal_full) if on and cal_full is not None else {})})
    if batch:
        rows.append({"trial": name, "method": "batch smooth", "smoothed_deg": _err(q_batch, s), "seconds": t_batch,
                     "rt_factor": s.n / s.rate / t_batch})
    q_vqf, t_vqf = timed(vqf_online, s)
    rows.append({"trial": name, "method": "online VQF", "filtered_deg": _err(q_vqf, s), "seconds": t_vqf,
                 "rt_factor": s.n / s.rate / t_vqf, **({"filtered_after_deg": _err_after(q_vqf, s, n_boot)} if after else {})})
    for r in rows:
        r.update(samples=s.n, rate_hz=round(s.rate, 1), bootstrap_samples=n_boot,
                 bootstrap_span_s=round(float(s.t[n_boot - 1] - s.t[0]), 1))
    return rows


def _cache_load(cache: str | None, name: str) -> dict | None:
    """--cache DIR: the trial's bootstrap (and whole-trial batch calibration) from an earlier run, cal_NN.pkl."""
    if not cache:
        return None
    p = Path(cache) / f"cal_{name}.pkl"
    return pickle.loads(p.read_bytes()) if p.exists() else None


def _cal_agreement(cal, ref) -> dict:
    """Streamed vs batch calibration: max over D, o of |difference| / sqrt(std_stream² + std_batch²)
    (`cal_z`), and the max relative difference of D (`cal_dD_rel`, of the field scale)."""
    def std(c, k, shape):
        return np.asarray(c.std.get(k, np.zeros(shape)), float) if c.std else np.zeros(shape)
    z = []
    for k, shape in (("D", (3, 3)), ("o", (3,))):
        diff = np.asarray(getattr(cal, k)) - np.asarray(getattr(ref, k))
        z.append((np.abs(diff) / np.sqrt(std(cal, k, shape) ** 2 + std(ref, k, shape) ** 2 + 1e-30)).ravel())
    scale = float(np.cbrt(abs(np.linalg.det(ref.D))))
    return {"cal_z": float(np.max(np.concatenate(z))), "cal_dD_rel": float(np.abs(cal.D - ref.D).max() / scale)}


def _whiteness(r, t, block: float = 2.0):
    """Batch-means whiteness factor per axis of the batch's whitened magnetometer residuals r (N, 3) over
    `block`-second blocks (stream_calib eq. 3: 1 for white residuals), floored at 1; None without residuals."""
    if r is None:
        return None
    ok = np.all(np.isfinite(r), axis=1)
    r, t = r[ok], t[ok]
    b = np.floor((t - t[0]) / block).astype(int)
    sums = np.zeros((b.max() + 1, 3))
    np.add.at(sums, b, r)
    return np.maximum((sums ** 2).sum(0) / (r ** 2).sum(0), 1.0)


def _last_refit(history: list, cal, ref, f_batch=None) -> dict:
    """The last online refit (applied or not) against the batch calibration, and how many were applied; with
    f_batch (per magnetometer axis, `_whiteness` of the batch's residuals) also `refit_z_bF`: the batch std of
    row j of D and o_j scaled by sqrt(F_j) (the batch's covariance assumes white residuals)."""
    from dataclasses import replace

    rows = [h for h in history if h.get("std")]
    if not rows:
        return {}
    h = rows[-1]
    last = replace(cal, D=np.asarray(h["D"]), o=np.asarray(h["o"]), std={k: np.asarray(v) for k, v in h["std"].items()})
    a = _cal_agreement(last, ref)
    out = {"refit_z": a["cal_z"], "refit_dD_rel": a["cal_dD_rel"], "applied": sum(bool(x.get("applied")) for x in history),
           "refits": len(history)}
    # the streamed std without the residual-whiteness factor (stream_calstate eq. 6 / stream_calib eq. 3): the
    # model's own std, as the batch reports its own
    white = replace(last, std={k: np.asarray(v) for k, v in h["std_white"].items()}) if h.get("std_white") else None
    if white is not None:
        out.update(refit_z_white=_cal_agreement(white, ref)["cal_z"], V_max=max(h["whiteness"]) if h.get("whiteness") else None)
    if f_batch is not None and ref.std:
        k = np.sqrt(f_batch)
        ref_f = replace(ref, std={"D": np.asarray(ref.std["D"]) * k[:, None], "o": np.asarray(ref.std["o"]) * k})
        out.update(refit_z_bF=_cal_agreement(last, ref_f)["cal_z"], F_batch_max=float(np.max(f_batch)))
        if white is not None:
            out.update(refit_z_white_bF=_cal_agreement(white, ref_f)["cal_z"])
    return out


def _white_z(history: list, cal, ref) -> dict:
    """cal_z of the end calibration with its white-noise std (stream_calib `std_white`, what the refit reported
    before the whiteness factor), and that factor's largest axis (`whiteness`)."""
    from dataclasses import replace

    rows = [h for h in history if h.get("applied") and h.get("std_white") and h.get("whiteness")]
    if not rows:
        return {}
    h = rows[-1]
    white = replace(cal, std={k: np.asarray(v) for k, v in h["std_white"].items()})
    return {"cal_z_white": _cal_agreement(white, ref)["cal_z"],
            "whiteness": max(h["whiteness"]) if h.get("whiteness") else None}


def _means(rows: list[dict]) -> list[dict]:
    """Per method: mean filtered and smoothed error, mean real-time factor, worst p99 over the trials."""
    out = []
    for m in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == m]
        def mean(key):
            v = [r[key] for r in sel if r.get(key) is not None]
            return float(np.mean(v)) if v else None
        def worst(key):
            v = [r[key] for r in sel if r.get(key) is not None]
            return max(v) if v else None
        out.append({"method": m, "trials": len(sel), "filtered_deg": mean("filtered_deg"),
                    "filtered_after_deg": mean("filtered_after_deg"),
                    "after_trials": sum(r.get("filtered_after_deg") is not None for r in sel),
                    "smoothed_deg": mean("smoothed_deg"), "rt_factor": mean("rt_factor"), "p99_ms": worst("p99_ms"),
                    "cpu_rt": mean("cpu_rt"), "p99_cpu_ms": worst("p99_cpu_ms"), "p99_btw_cpu_ms": worst("p99_btw_cpu_ms")})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="01")
    ap.add_argument("--lag", type=float, default=2.0)
    ap.add_argument("--no-lag", action="store_true")
    ap.add_argument("--no-batch", action="store_true")
    ap.add_argument("--bootstrap-s", type=float, default=30.0)
    ap.add_argument("--calibration", choices=("online", "fixed", "both"), default="online",
                    help="online re-estimation of D, o (default), the bootstrap held fixed, or both runs")
    ap.add_argument("--lag-solver", choices=("chain", "incremental", "batch"), default="chain",
                    help="stream_lag.ChainLagSmoother (default), gtsam IncrementalFixedLagSmoother or "
                         "BatchFixedLagSmoother for --lag")
    ap.add_argument("--lag-only", action="store_true", help="skip the full iSAM2 run")
    ap.add_argument("--no-cal-compare", action="store_true", help="skip the whole-trial batch calibration")
    from imugraph.graphs.stream import StreamOptions

    ap.add_argument("--calib-states", action=argparse.BooleanOptionalAction, default=StreamOptions.calib_states, help="online calibration with θ as a graph state "
                    "(StreamOptions(calib_states=True)) instead of the closed-form refit on fixed orientations")
    ap.add_argument("--disturb", action=argparse.BooleanOptionalAction, default=StreamOptions.disturb_detect, help="causal disturbance windows left out of the online "
                    "calibration (StreamOptions(disturb_detect=True), imugraph.graphs.stream_disturb)")
    ap.add_argument("--weak-prior", action="store_true", help="the batch's weak prior for the online calibration "
                    "when the bootstrap says D, o are not identifiable (StreamOptions(calib_weak_prior=True))")
    ap.add_argument("--offsets", action=argparse.BooleanOptionalAction, default=StreamOptions.disturb_offsets, help="with --calib-states --disturb: each disturbance window "
                    "its own hard-iron offset, the reported hard iron the majority's (StreamOptions(disturb_offsets=True))")
    ap.add_argument("--cache", default=None, help="DIR: reuse / store each trial's bootstrap and whole-trial batch "
                    "calibration (cal_NN.pkl; the calibration code may have changed since they were computed)")
    ap.add_argument("--bootstrap-max-s", type=float, default=None, metavar="S",
                    help="cap the bootstrap window's growth at S seconds (bootstrap_calibration max_s: at the cap the "
                         "weak fallback of calibrate); default: grows until identified or the trial ends")
    ap.add_argument("--bootstrap-regrow", choices=("off", "identified", "weak"), default="off",
                    help="with a capped bootstrap's weak start: keep growing the bootstrap while streaming and switch "
                         "to the first window that identifies D, o ('identified'), or also to each longer window's "
                         "weak fallback ('weak') (stream_session bootstrap_regrow; helper S22). Default off")
    ap.add_argument("--bootstrap-weak-centre", action="store_true",
                    help="a weak (not identifiable) bootstrap streamed at its weak prior's centre D = s·I, o = 0 "
                         "(stream_session bootstrap_weak_centre, stream_run.weak_centre; helper S22)")
    ap.add_argument("--regrow-align", action="store_true", help="stream_session regrow_align (helper S22)")
    ap.add_argument("--regrow-grow", type=float, default=1.5, help="stream_session regrow_grow (default 1.5)")
    ap.add_argument("--regrow-confirm", type=float, default=None, help="stream_session regrow_confirm (helper S23)")
    ap.add_argument("--regrow-latency", type=float, default=None, help="stream_session regrow_latency_s (repeatable)")
    ap.add_argument("--out", default="stream_speed.json", help="file name under bench_out/ (default stream_speed.json)")
    ap.add_argument("--score-after-bootstrap", action="store_true",
                    help="also score the filtered output (and online VQF) only on the movement samples after each "
                         "trial's bootstrap window (`filtered_after_deg`; none when the bootstrap took the whole trial)")
    ap.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                    help="a further StreamOptions field (Python literal), e.g. disturb_learn_sigma=False")
    a = ap.parse_args(argv)
    extra = stream_overrides(a.opt)
    every = a.trials == "all"
    wanted = set() if every else {int(x) for x in a.trials.split(",")}
    paths = [p for p in broad_trials() if every or trial_number(p) in wanted]
    if not paths:
        print(f"no BROAD trial {a.trials} in the data folder", file=sys.stderr)
        return 2
    lag = None if a.no_lag else a.lag
    rows = []
    for p in paths:
        online = {"online": (True,), "fixed": (False,), "both": (True, False)}[a.calibration]
        rows += run_trial(p, lag, a.bootstrap_s, not a.no_batch, online, not a.no_cal_compare, a.lag_solver, a.lag_only,
                          a.calib_states, a.disturb, a.weak_prior, a.cache, a.offsets, extra, a.bootstrap_max_s,
                          a.score_after_bootstrap, {"off": False, "identified": True, "weak": "weak"}[a.bootstrap_regrow],
                          a.bootstrap_weak_centre, {"regrow_align": a.regrow_align, "regrow_grow": a.regrow_grow,
                                                    "regrow_confirm": a.regrow_confirm,
                                                    "regrow_latency_s": a.regrow_latency})
        print(f"trial {trial_number(p):02d} done", file=sys.stderr, flush=True)
    cols = ["trial", "method", "rt_factor", "p50_ms", "p99_ms", "cpu_rt", "p99_cpu_ms", "max_cpu_ms", "p99_btw_cpu_ms",
            "max_btw_cpu_ms", "filtered_deg", "filtered_after_deg", "bootstrap_span_s", "smoothed_deg", "vs_batch_deg", "E_max",
            "seconds", "bootstrap_s", "failed", "dist", "dist_kf", "cal_z", "cal_z_white", "whiteness", "cal_dD_rel", "refit_z", "refit_z_bF",
            "refit_z_white", "refit_z_white_bF", "V_max", "F_batch_max", "refit_dD_rel",
            "applied", "refits", "regrow_switches", "regrow_last_switch_s", "regrow_identified", "regrow_cpu_s"]
    print_table(rows, cols)
    means = _means(rows)
    print_table(means, ["method", "trials", "filtered_deg", "filtered_after_deg", "after_trials", "smoothed_deg", "rt_factor", "p99_ms", "cpu_rt", "p99_cpu_ms",
                        "p99_btw_cpu_ms"])
    print(f"peak memory {peak_memory_mb():.0f} MB")
    write_json(a.out, {"rows": rows, "means": means, "lag_s": lag, "bootstrap_s": a.bootstrap_s,
                                "bootstrap_max_s": a.bootstrap_max_s, "bootstrap_regrow": a.bootstrap_regrow,
                                "command": " ".join(sys.argv)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
