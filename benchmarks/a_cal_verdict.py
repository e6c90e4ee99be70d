"""Issue 3, task A: why the streamed calibration of BROAD 36 left the batch's reported std when
`calibration.ml.Options.window_trial_verdict` became the default (z 2.78 → 3.08).

A 2 × 2 design per trial: the stream's bootstrap (first ≥ 30 s, `stream_run.bootstrap_calibration`) and the
whole-trial batch `calibrate` (as benchmarks/stream_speed.py: `Options()`, allow_weak on CalibrationError), each with
window_trial_verdict True (the default) and False. The stream (default `StreamOptions`, chain lag 2 s) runs once per
bootstrap and its end calibration is compared with both batches:

    z_ij = |θ_s,i − θ_b,j| / sqrt(std_s,i² + std_b,j²)        over the 12 entries of D and o (stream_speed._cal_agreement)

reported as the max (`z`, the worst entry named) with the stream's reported std, and with its model std
(`z_white`, std_white of the last history row). Also per calibration: its field scale |det D|^(1/3), the number
of disturbance windows and the fraction of rows they leave out (not modelled, or a modelled window's left_out).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/a_cal_verdict.py 36 [--cache DIR] [--oracle]

TRIALS: comma-separated BROAD numbers or "all". --cache keeps the four calibrations per trial (a_cal_NN.pkl).
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import broad_trials, load_broad_trial, print_table, trial_number  # noqa: E402

ENTRIES = [f"D{i}{j}" for i in "xyz" for j in "xyz"] + [f"o{i}" for i in "xyz"]


def z_entries(cal, ref, std_s: dict | None = None) -> np.ndarray:
    """|cal − ref| / sqrt(std_s² + std_ref²) per entry of D (row-major) and o: (12,)."""
    std_s = cal.std if std_s is None else std_s
    out = []
    for k in ("D", "o"):
        d = np.asarray(getattr(cal, k), float) - np.asarray(getattr(ref, k), float)
        out.append((np.abs(d) / np.sqrt(np.asarray(std_s[k], float) ** 2 + np.asarray(ref.std[k], float) ** 2)).ravel())
    return np.concatenate(out)


def left_out_fraction(cal, t: np.ndarray) -> float:
    """Fraction of the rows t that the calibration's windows leave out (`Calibration.corrected` sets them NaN)."""
    out = np.zeros(len(t), bool)
    for d in cal.disturbances:
        inside = (t >= d["t_start"]) & (t <= d["t_end"])
        if d.get("modelled") and d.get("offset") is not None:
            for a, b in d.get("left_out") or ():
                out |= (t >= a) & (t <= b)
        else:
            out |= inside
    return float(out.mean())


def calibrations(s, name: str, cache: str | None) -> dict:
    """Bootstrap and whole-trial batch with window_trial_verdict True / False (cached)."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.errors import CalibrationError
    from imugraph.graphs.stream_run import bootstrap_calibration

    p = Path(cache) / f"a_cal_{name}.pkl" if cache else None
    if p is not None and p.exists():
        return pickle.loads(p.read_bytes())
    out = {}
    for v in (True, False):
        out[("boot", v)] = bootstrap_calibration(s, 30.0, overrides={"window_trial_verdict": v})
        opt = replace(Options(), window_trial_verdict=v)
        try:
            out[("full", v)] = calibrate(s, opt).calibration
        except CalibrationError:
            out[("full", v)] = calibrate(s, opt, allow_weak=True).calibration
    if p is not None:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(pickle.dumps(out))
    return out


def run_trial(path: Path, cache: str | None) -> list[dict]:
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import stream_session

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    cals = calibrations(s, name, cache)
    rows = []
    for v in (True, False):
        boot, n_boot = cals[("boot", v)]
        r = stream_session(s, None, StreamOptions(lag_s=2.0, fixed_lag_solver="chain"), 30.0, bootstrap=(boot, n_boot))
        h = [x for x in r.calibration_history if x.get("std_white")]
        for w in (True, False):
            ref = cals[("full", w)]
            z = z_entries(r.calibration, ref)
            zw = z_entries(r.calibration, ref, h[-1]["std_white"]) if h else np.full(12, np.nan)
            zb = z_entries(boot, ref)
            scale = lambda c: float(np.cbrt(abs(np.linalg.det(c.D))))   # noqa: E731
            rows.append({"trial": name, "boot_verdict": v, "batch_verdict": w, "z": float(z.max()),
                         "worst": ENTRIES[int(z.argmax())], "z_white": float(np.nanmax(zw)),
                         "z_boot": float(zb.max()), "scale_stream": scale(r.calibration), "scale_boot": scale(boot),
                         "scale_batch": scale(ref), "boot_s": float(s.t[n_boot - 1] - s.t[0]),
                         "boot_windows": len(boot.disturbances), "boot_left_out": left_out_fraction(boot, s.t[:n_boot]),
                         "batch_windows": len(ref.disturbances), "batch_left_out": left_out_fraction(ref, s.t),
                         "filtered_deg": _err(r.filtered, s)})
    return rows


def oracle_rows(path: Path, cache: str | None) -> list[dict]:
    """--oracle: the stream (default options) from starts that mix the bootstrap (verdict True) with the batch's
    answers, against the batch (verdict True): which part of the disagreement is the start calibration's D, o and
    which the disturbance windows (the stream applies its start calibration's windows at any time, so a start
    carrying the batch's 24 windows leaves out what the batch leaves out). Oracles: diagnosis only."""
    from imugraph.graphs.stream import StreamOptions
    from imugraph.graphs.stream_run import stream_session

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    cals = calibrations(s, name, cache)
    boot, n_boot = cals[("boot", True)]
    ref = cals[("full", True)]
    starts = {"bootstrap": boot,
              "bootstrap D,o + batch windows": replace(boot, disturbances=ref.disturbances),
              "batch D,o,dip + bootstrap windows": replace(boot, D=ref.D, o=ref.o, dip_deg=ref.dip_deg),
              "batch D,o,dip + batch windows": replace(boot, D=ref.D, o=ref.o, dip_deg=ref.dip_deg,
                                                       disturbances=ref.disturbances)}
    rows = []
    for label, start in starts.items():
        r = stream_session(s, None, StreamOptions(lag_s=2.0, fixed_lag_solver="chain"), 30.0, bootstrap=(start, n_boot))
        h = [x for x in r.calibration_history if x.get("std_white")]
        z = z_entries(r.calibration, ref)
        zw = z_entries(r.calibration, ref, h[-1]["std_white"])
        rows.append({"trial": name, "start": label, "z": float(z.max()), "worst": ENTRIES[int(z.argmax())],
                     "z_white": float(zw.max()), "dD_rel": float(np.abs(r.calibration.D - ref.D).max()
                                                             / np.cbrt(abs(np.linalg.det(ref.D)))),
                     "do_rel": float(np.abs(r.calibration.o - ref.o).max() / np.cbrt(abs(np.linalg.det(ref.D)))),
                     "V_max": max(h[-1]["whiteness"]), "filtered_deg": _err(r.filtered, s)})
    return rows


def _err(q, s) -> float:
    from imugraph.evaluate import orientation_error
    return orientation_error(q, s.quat, s.movement, s.rate).rms_deg


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="?", default="36")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--oracle", action="store_true", help="the start-vs-windows decomposition (oracle_rows)")
    a = ap.parse_args(argv)
    every = a.trials == "all"
    wanted = set() if every else {int(x) for x in a.trials.split(",")}
    rows = []
    for p in broad_trials():
        if every or trial_number(p) in wanted:
            rows += oracle_rows(p, a.cache) if a.oracle else run_trial(p, a.cache)
            print(f"trial {trial_number(p):02d} done", file=sys.stderr, flush=True)
    print_table(rows, list(rows[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
