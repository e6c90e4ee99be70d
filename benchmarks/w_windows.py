"""Issue 3, session 18 (helper W): the stream's disturbance windows against the batch's, per BROAD trial.

Per trial (cached bootstrap and whole-trial batch calibration, as stream_vs_batch.py --cache): the stream under full
iSAM2 with StreamOptions(windows_end=True) (its filtered pass is the default's: the option touches only the end graph),
then printed side by side (times in s since the trial's first sample):
    batch     the whole-trial batch calibration's `disturbances` (modelled: offset kept; else left out)
    start     the bootstrap calibration's own windows (the stream applies them: fixed offset or left out)
    detector  the stream's causal detector windows (runs of keyframes whose factor carried one Δo_w)
    end       the windows re-derived at the end from the whole stream (stream_windows_end), with their verdict
and the overlap (seconds) of each list's MODELLED / LEFT-OUT time with the batch's.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/w_windows.py 32,34,36 --cache /tmp/A_cache [--out NAME]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import load_broad_trial, select_trials, trial_number  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks.stream_vs_batch import calibrations, stream_with_recorder  # noqa: E402


def spans(ws: list[dict], modelled: bool | None) -> list[tuple[float, float]]:
    """(t_start, t_end) of the windows with that verdict (None: all)."""
    return [(d["t_start"], d["t_end"]) for d in ws if modelled is None or bool(d.get("modelled", True)) == modelled]


def covered(t: np.ndarray, sp: list) -> np.ndarray:
    m = np.zeros(len(t), bool)
    for a, b in sp:
        m |= (t >= a) & (t <= b)
    return m


def run(path: Path, cache: str | None) -> dict:
    from imugraph.graphs.stream import StreamOptions

    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    boot, n_boot, full, _, _ = calibrations(s, name, cache, 30.0)
    c0 = time.process_time()
    r, sm = stream_with_recorder(s, StreamOptions(lag_s=None, windows_end=True), 30.0, boot, n_boot)
    cpu = time.process_time() - c0
    ext = sm._end_extensions[-1]
    rep = ext.report
    t0 = float(s.t[0])
    lists = {"batch": list(full.disturbances), "start": rep.get("start", []),
             "detector": [dict(d, modelled=True) for d in rep.get("detector", [])], "end": rep.get("windows", [])}
    print(f"--- trial {name}: stream CPU {cpu:.1f} s, end rounds {rep.get('rounds')}")
    dt = 1.0 / s.rate
    row = {"trial": name, "stream_cpu_s": cpu}
    for lab, ws in lists.items():
        for d in ws:
            off = d.get("offset")
            print(f"  {lab:8s} {d['t_start'] - t0:8.2f} – {d['t_end'] - t0:8.2f}  "
                  f"{'modelled' if d.get('modelled', True) else 'left out'}"
                  + ("" if off is None else f"  |Δo| {np.linalg.norm(off):6.2f}"))
        if lab != "batch":      # agreement with the batch's, in seconds of samples (the stream's own causal union)
            for v in (True, False):
                a, b = covered(s.t, spans(lists["batch"], v)), covered(s.t, spans(ws, v))
                row[f"{lab}_{'mod' if v else 'out'}_both_s"] = float((a & b).sum() * dt)
                row[f"{lab}_{'mod' if v else 'out'}_batch_only_s"] = float((a & ~b).sum() * dt)
                row[f"{lab}_{'mod' if v else 'out'}_own_only_s"] = float((~a & b).sum() * dt)
    row["lists"] = {k: [{kk: (vv - t0 if kk in ("t_start", "t_end") else vv) for kk, vv in d.items()
                         if kk in ("t_start", "t_end", "modelled")} for d in v] for k, v in lists.items()}
    print("  overlap with the batch (s), modelled both / batch only / own only; left out the same:")
    for lab in ("start", "detector", "end"):
        print(f"  {lab:8s} mod {row[f'{lab}_mod_both_s']:6.1f} / {row[f'{lab}_mod_batch_only_s']:6.1f} / "
              f"{row[f'{lab}_mod_own_only_s']:6.1f}   out {row[f'{lab}_out_both_s']:6.1f} / "
              f"{row[f'{lab}_out_batch_only_s']:6.1f} / {row[f'{lab}_out_own_only_s']:6.1f}")
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trials", nargs="?", default="32,34,36")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--out", default="w_windows.json")
    a = ap.parse_args(argv)
    rows = []
    for path in select_trials(a.trials):
        rows.append(run(path, a.cache))
        write_json(a.out, rows)


if __name__ == "__main__":
    main()
