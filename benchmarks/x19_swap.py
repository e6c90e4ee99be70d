"""Issue 3 attribution (session 19, helper X): which part of the stream's END model keeps it > 0.1° from the batch.

Per BROAD trial (calibrations as benchmarks/stream_vs_batch.py: --cache DIR with cal_NN.pkl, boot = the stream's
30 s bootstrap, full = the batch calibration `calibrate(s, Options())`):
    stream     the default stream (StreamOptions(lag_s=None): full iSAM2, the session-18 end-graph extensions),
               run with stream_vs_batch.stream_with_recorder
    end model  its END calibration built exactly as stream_vs_batch.same_model does: end_graph_calibration (the end θ),
               _learned_changes (Ê, σ̂_v τ̂_v), stream_windows_end.end_calibration (the end windows as
               `disturbances`); the rest (noise levels, gyro bias, lag, acc lead) is the bootstrap's
    batch      q_full_field = smooth_fixed(s, full, keyframe_hz=kf, field_sigma=Options().field_sigma,
               field_tau=Options().field_tau) (what `imugraph smooth --calibration` runs; the brief's reference)
Every variant below is smoothed IN THAT SAME CALL FORM (only the Calibration differs), so "end+all" reproduces
q_full_field exactly, and scored heading-aligned against q_full_field over `movement`
(stream_vs_batch.rms_between(heading=True), degrees):
    stream      the stream's own smoothed output (= the brief's vs_batch_field_h_deg)
    end         the end model as is (one model, two solvers, in the batch's magnetometer form)
    end+G       the end model with group G taken from `full`;   end+all: every group from `full` (must be 0)
    full+G      the batch model with group G taken from the end model (the reverse view)
Groups (Calibration fields; smooth_fixed reads nothing else):
    theta (D, o, dip_deg), noise (noise: gyr/acc/mag σ, and coverage, whose only smoothing use is the optional
    noise_correlation inflation), windows (disturbances), gyro_map (E), velocity (velocity_sigma, velocity_tau),
    timing (mag_delay_s, acc_lead_samples), bias (gyro_bias).
    end+D, end+o, end+dip_deg, full+D, ...: θ's parts alone.
    greedy      forward selection: the best single end+G, then the group that lowers the score most given those
                already swapped, until ≤ 0.02° or four groups ([[group, score], ...]; catches interactions).
    refine      per group of the greedy path with parts (θ: D/o/dip; noise: gyr/acc/mag σ; velocity: σ_v/τ_v;
                timing: mag_delay_s/acc_lead_samples): the path's final set with that group replaced by one part.
Batch reproducibility floor (--floor, on by default): the batch calibration re-run under nuisance choices, smoothed
the same way and scored against q_full_field — how far the batch's own answer moves:
    floor_rtol  q_full_field's own smooth solved to convergence (rotation_tol_deg=0.001, as same_model; the CLI's
                default 0.05° stops earlier) — the batch path's solver floor
    floor_kf10  calibrate(s, Options(keyframe_hz=kf)) (the stream's keyframe spacing, 10 Hz, instead of 5 Hz)
    floor_tol   calibrate(s, Options(noise_tol=Options().noise_tol / 10)) (the ML rounds' stopping tolerance)
    stream_vs_kf10, stream_vs_tol: the stream scored against those two floor batches instead
    (CalibrationError → allow_weak=True, as stream_vs_batch.calibrations; cached in --floor-cache DIR as
    floor_NN.pkl when given.)

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/x19_swap.py 02,04,07,12,24,26,32,34,36 --cache /tmp/A_cache
        [--floor-cache DIR] [--no-floor] [--out x19_swap.json] [--config NAME]

--config: the stream's StreamOptions as stream_vs_batch.CONFIGS[NAME] (default "default" = the session-18 defaults);
the end model then carries whatever that config's end graph learned (`_learned_changes`).

Writes bench_out/NAME (default x19_swap.json) after every trial (rows so far, the group values end vs full).
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import load_broad_trial, print_table, select_trials, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.stream_vs_batch import (CONFIGS, calibrations, end_model_calibration, rms_between,  # noqa: E402
                                        stream_with_recorder)

# the Calibration fields of each swap group (module docstring)
GROUPS = {"theta": ("D", "o", "dip_deg"), "noise": ("noise", "coverage"), "windows": ("disturbances",),
          "gyro_map": ("gyro_map",), "velocity": ("velocity_sigma", "velocity_tau"),
          "timing": ("mag_delay_s", "acc_lead_samples"), "bias": ("gyro_bias",)}
ALL_FIELDS = tuple(f for fs in GROUPS.values() for f in fs)


def swap(base, donor, fields) -> object:
    """`base` with the given Calibration fields taken from `donor`; "noise.mag" (.gyr, .acc): one sensor's σ only."""
    changes: dict = {}
    for f in fields:
        if f.startswith("noise."):
            k = f.split(".", 1)[1]
            changes["noise"] = {**changes.get("noise", base.noise), k: donor.noise[k]}
        else:
            changes[f] = getattr(donor, f)
    return replace(base, **changes)


# the parts of a group that `refine` tries alone (the others of the group stay the end model's)
PARTS = {"theta": ("D", "o", "dip_deg"), "noise": ("noise.gyr", "noise.acc", "noise.mag"),
         "velocity": ("velocity_sigma", "velocity_tau"), "timing": ("mag_delay_s", "acc_lead_samples")}


def end_model(s, opts, bootstrap_s, boot, n_boot):
    """(stream result, smoother, end Calibration) — the end calibration as stream_vs_batch.same_model builds it:
    the end θ (end_graph_calibration), Ê and σ̂_v τ̂_v (_learned_changes), the end windows (end_calibration)."""
    r, sm = stream_with_recorder(s, opts, bootstrap_s, boot, n_boot)
    _, _, cal, cal_end = end_model_calibration(boot, sm, r, opts)
    return r, sm, (cal_end if cal_end is not None else cal)


def floor_calibrations(s, name: str, cache: str | None, kf: float) -> dict:
    """{"floor_kf10": Calibration, "floor_tol": Calibration, "cpu_s": {...}}: the batch calibration under nuisance
    choices (module docstring); read from / written to cache/floor_NN.pkl."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.errors import CalibrationError

    p = Path(cache) / f"floor_{name}.pkl" if cache else None
    if p is not None and p.exists():
        return pickle.loads(p.read_bytes())
    out: dict = {"cpu_s": {}}
    for key, o in (("floor_kf10", Options(keyframe_hz=kf)), ("floor_tol", Options(noise_tol=Options().noise_tol / 10))):
        t0 = time.process_time()
        try:
            out[key] = calibrate(s, o).calibration
        except CalibrationError:                 # too little rotation: the regularised estimate, as --allow-weak
            out[key] = calibrate(s, o, allow_weak=True).calibration
        out["cpu_s"][key] = time.process_time() - t0
    if p is not None:
        from imugraph.io.writers import atomic_write_bytes
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(p, pickle.dumps(out))
    return out


def greedy(row: dict, score_of, steps: int = 4, enough: float = 0.02) -> list:
    """Forward selection of swap groups (end+G…): start from the best single swap (row's end+G), then add the group
    that lowers the score most given those already swapped, until the score ≤ `enough` or `steps` groups;
    [[group, score after adding it], ...]. Catches interactions the single swaps miss (BROAD 36)."""
    chosen = [min(GROUPS, key=lambda g: row[f"end+{g}"])]
    path = [[chosen[0], row[f"end+{chosen[0]}"]]]
    while len(chosen) < steps and path[-1][1] > enough:
        trial = {g: score_of(chosen + [g]) for g in GROUPS if g not in chosen}
        g = min(trial, key=trial.get)
        chosen.append(g)
        path.append([g, trial[g]])
    return path


def refine(path: list, score_of) -> dict:
    """For each group g of the greedy path with parts (PARTS): the path's final set with g replaced by one part of g
    {g: {part: score}} — which part of g carries its share (e.g. 36's noise: the magnetometer's σ?)."""
    groups = [g for g, _ in path]
    out: dict = {}
    for g in groups:
        for part in PARTS.get(g, ()):
            fields = [f for h in groups if h != g for f in GROUPS[h]] + [part]
            out.setdefault(g, {})[part] = score_of(fields)
    return out


def _describe(cal) -> dict:
    """The group values of a calibration, for the JSON (what differs between end and full)."""
    win = [(round(d["t_start"], 2), round(d["t_end"], 2), bool(d.get("modelled"))) for d in cal.disturbances]
    return {"D": np.asarray(cal.D).tolist(), "o": np.asarray(cal.o).tolist(), "dip_deg": cal.dip_deg,
            "noise": {k: np.asarray(v).tolist() for k, v in cal.noise.items()},
            "noise_correlation": (cal.coverage or {}).get("noise_correlation"), "windows": win,
            "gyro_map_diag": np.diag(np.asarray(cal.gyro_map)).tolist(),
            "velocity": [cal.velocity_sigma, cal.velocity_tau], "mag_delay_s": cal.mag_delay_s,
            "acc_lead_samples": cal.acc_lead_samples, "gyro_bias": np.asarray(cal.gyro_bias).tolist()}


def run_trial(path: Path, cache: str | None, floor_cache: str | None, floor: bool, bootstrap_s: float,
              config: str = "default") -> dict:
    """Every variant of the module docstring for one trial: one row {variant: degrees, ...}."""
    from imugraph.calibration.ml import Options
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.graphs.stream import StreamOptions

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    boot, n_boot, full, _, _ = calibrations(s, name, cache, bootstrap_s)
    opts = StreamOptions(lag_s=None, **CONFIGS[config])
    kf = opts.keyframe_hz
    # the batch path's call form (stream_vs_batch.run_trial's q_full_field); every variant uses it
    form = dict(keyframe_hz=kf, field_sigma=Options().field_sigma, field_tau=Options().field_tau)
    t0 = time.process_time()
    q_full = smooth_fixed(s, full, **form)
    smooth_cpu = time.process_time() - t0

    def score(q):
        return rms_between(q, q_full, s.movement, s.rate, heading=True)

    t0 = time.process_time()
    r, sm, end = end_model(s, opts, bootstrap_s, boot, n_boot)
    stream_cpu = time.process_time() - t0
    row = {"trial": name, "config": config, "stream": score(r.smoothed)}
    q_end = smooth_fixed(s, end, **form)
    row["end"] = score(q_end)
    row["end_vs_stream"] = rms_between(q_end, r.smoothed, s.movement, s.rate, heading=True)
    done: dict = {}

    def end_with(fields) -> float:
        """score of the end model with these fields from `full`; memoised (refine revisits θ's single parts)."""
        key = frozenset(fields)
        if key not in done:
            done[key] = score(smooth_fixed(s, swap(end, full, fields), **form))
        return done[key]

    for g, fields in GROUPS.items():
        row[f"end+{g}"] = end_with(fields)
    row["end+all"] = end_with(ALL_FIELDS)
    for g, fields in GROUPS.items():
        row[f"full+{g}"] = score(smooth_fixed(s, swap(full, end, fields), **form))
    # θ's parts alone, both directions
    for part in GROUPS["theta"]:
        row[f"end+{part}"] = end_with((part,))
        row[f"full+{part}"] = score(smooth_fixed(s, swap(full, end, (part,)), **form))
    row["greedy"] = greedy(row, lambda gs: end_with([f for g in gs for f in GROUPS[g]]))
    row["refine"] = refine(row["greedy"], end_with)
    # the batch path's own solve to convergence (same_model's rotation_tol_deg; the CLI's 0.05° stops earlier)
    row["floor_rtol"] = score(smooth_fixed(s, full, **form, rotation_tol_deg=0.001))
    floor_cpu = {}
    if floor:
        fl = floor_calibrations(s, name, floor_cache, kf)
        floor_cpu = fl["cpu_s"]
        for key in ("floor_kf10", "floor_tol"):
            q = smooth_fixed(s, fl[key], **form)
            row[key] = score(q)
            # the stream and the end model against that floor batch (is the stream nearer the 10 Hz batch?)
            row[f"stream_vs_{key[6:]}"] = rms_between(r.smoothed, q, s.movement, s.rate, heading=True)
    row.update(smooth_cpu_s=smooth_cpu, stream_cpu_s=stream_cpu, floor_cpu_s=floor_cpu,
               end_cal=_describe(end), full_cal=_describe(full))
    return row


VARIANTS = (["stream", "end", "end_vs_stream"] + [f"end+{g}" for g in GROUPS] + ["end+all"]
            + [f"end+{p}" for p in GROUPS["theta"]] + [f"full+{g}" for g in GROUPS]
            + [f"full+{p}" for p in GROUPS["theta"]] + ["floor_rtol", "floor_kf10", "floor_tol", "stream_vs_kf10",
                                                         "stream_vs_tol"])


def main(argv: list[str] | None = None) -> int:
    """Run the trials one after the other; print the trial × variant table (degrees)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="all")
    ap.add_argument("--cache", default=None, help="folder of cal_NN.pkl (stream_vs_batch.py --cache)")
    ap.add_argument("--floor-cache", default=None, help="folder for floor_NN.pkl (the floor's calibrations)")
    ap.add_argument("--no-floor", action="store_true", help="skip the batch reproducibility floor")
    ap.add_argument("--bootstrap-s", type=float, default=30.0)
    ap.add_argument("--out", default="x19_swap.json")
    ap.add_argument("--config", default="default", help="the stream's options: a name of stream_vs_batch.CONFIGS")
    a = ap.parse_args(argv)
    rows: list[dict] = []
    for p in select_trials(a.trials):
        rows.append(run_trial(p, a.cache, a.floor_cache, not a.no_floor, a.bootstrap_s, a.config))
        r = rows[-1]
        print(r["trial"], " ".join(f"{k} {r[k]:.3f}" for k in VARIANTS if k in r), "| greedy",
              " → ".join(f"{g} {v:.3f}" for g, v in r["greedy"]), "| refine",
              "; ".join(f"{g}: " + ", ".join(f"{p} {v:.3f}" for p, v in d.items()) for g, d in r["refine"].items()),
              f"| stream cpu {r['stream_cpu_s']:.0f} s, floor cpu {r['floor_cpu_s']}",
              flush=True)
        write_json(a.out, {"rows": rows, "groups": GROUPS, "variants": VARIANTS})
    half = 14
    for cols in (VARIANTS[:half], VARIANTS[half:]):
        print_table(rows, ["trial"] + [c for c in cols if any(c in r for r in rows)])
    return 0


if __name__ == "__main__":
    sys.exit(main())
