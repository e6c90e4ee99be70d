"""Task K (issue 3): how fast the stream recovers after each long sample drop, per StreamOptions variant.

For each BROAD trial and each variant (`--variant "key=value;key=value"`, repeatable; "" is the default
stream) two streams through the default 2 s chain lag with the `stream_arrival` set-up (bootstrap 30 s,
magnetometer at ¼ rate): `clean` (every sample) and `drop` (the three seeded drops of `stream_arrival`
`--kinds drop`, `--drop-s` long). Printed per run: the filtered / smoothed RMS error over `movement`
(stream_arrival.score), and per drop the filtered error's RMS in windows after the drop's end (0–1, 1–2,
2–5, 5–10, 10–20 s) for the dropped run next to the clean run of the same variant, and `rec`: the time after
the drop's end from which the dropped run's 1 s moving RMS stays within 3° of the clean run's (up to 20 s or
the next drop; ">W" when it never does). The per-sample error is the total rotation angle against opt_quat
after the run's own best constant heading offset (imugraph.evaluate.orientation_error; time shift 0).
Scoring only: the estimator never sees the truth.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/k3_recovery.py 06 --variant "" \
        --variant "position_sigma=0.3" [--drop-s 0.5] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import load_broad_trial, stream_overrides, trial_number  # noqa: E402
from benchmarks.stream_arrival import BOOTSTRAP_S, arrivals, score, stream, trial_paths  # noqa: E402
from imugraph.evaluate import orientation_error  # noqa: E402
from imugraph.geometry import quat_conj, quat_mul  # noqa: E402
from imugraph.graphs.stream import StreamOptions  # noqa: E402
from imugraph.graphs.stream_run import bootstrap_calibration  # noqa: E402

WINDOWS = ((0, 1), (1, 2), (2, 5), (5, 10), (10, 20))
REC_TOL_DEG, REC_MAX_S = 3.0, 20.0


def parse_variant(text: str) -> dict:
    """"k=v;k=v" → {k: literal v}; "" → {}."""
    return stream_overrides([kv for kv in text.split(";") if kv.strip()])


def per_sample_error(q: np.ndarray, s) -> np.ndarray:
    """(n,) degrees: angle of Rz(ψ)·nRb_est against opt_quat, ψ the run's best heading offset over `movement`
    (rows the run did not deliver: their nearest earlier delivered row, as stream_arrival.score)."""
    ok = np.isfinite(q[:, 0])
    idx = np.maximum.accumulate(np.where(ok, np.arange(len(q)), 0))
    idx[:np.argmax(ok)] = np.argmax(ok)
    qf = q[idx] / np.linalg.norm(q[idx], axis=1, keepdims=True)
    psi = np.radians(orientation_error(qf, s.quat, s.movement & ok, s.rate).heading_offset_deg)
    rz = np.tile([np.cos(psi / 2), 0.0, 0.0, np.sin(psi / 2)], (len(qf), 1))
    ref = s.quat / np.linalg.norm(s.quat, axis=1, keepdims=True)
    e = quat_mul(quat_conj(ref), quat_mul(rz, qf))
    return np.degrees(2.0 * np.arctan2(np.linalg.norm(e[:, 1:], axis=1), np.abs(e[:, 0])))


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if len(x) else float("nan")


def recovery(err_drop: np.ndarray, err_clean: np.ndarray, t: np.ndarray, t_end: float, t_stop: float) -> str:
    """Seconds after t_end from which the 1 s moving RMS of err_drop stays within REC_TOL_DEG of err_clean's."""
    sel = (t >= t_end) & (t < t_stop)
    n = max(1, int(round(1.0 / np.median(np.diff(t)))))
    kernel = np.ones(n) / n
    d = np.sqrt(np.convolve(np.nan_to_num(err_drop[sel]) ** 2, kernel, mode="same"))
    c = np.sqrt(np.convolve(np.nan_to_num(err_clean[sel]) ** 2, kernel, mode="same"))
    bad = np.flatnonzero(d > c + REC_TOL_DEG)
    if not len(bad):
        return "0.0"
    if bad[-1] >= len(d) - n:
        return f">{t_stop - t_end:.0f}"
    return f"{t[sel][bad[-1]] - t_end:.1f}"


def run(path: Path, variants: list[str], drop_s: float, seed: int) -> None:
    s = load_broad_trial(path)
    name = f"{trial_number(path):02d}"
    cal, n_boot = bootstrap_calibration(s, BOOTSTRAP_S)
    mag4 = s.mag.copy()
    mag4[np.arange(s.n) % 4 != 0] = np.nan
    try:
        order, _ = arrivals(s.n, s.rate, n_boot, np.random.default_rng(seed), frozenset({"drop"}), drop_s)
    except ValueError:          # no room for the drops after the bootstrap (stream_arrival's margins)
        print(f"trial {name}: too short for the drop schedule, skipped", flush=True)
        return
    cuts = [(a, b) for a, b in zip(order[:-1], order[1:]) if b - a > 1]     # (last before, first after)
    for text in variants:
        opts = StreamOptions(**{"lag_s": 2.0, **parse_variant(text)})
        out = {}
        for label, ordr in (("clean", list(range(s.n))), ("drop", order)):
            c0 = time.process_time()
            r = stream(s, cal, n_boot, ordr, mag4, set(), opts)
            out[label] = (r, time.process_time() - c0)
        err = {k: per_sample_error(v[0]["filtered"], s) for k, v in out.items()}
        for label, (r, cpu) in out.items():
            print(f"trial {name} variant [{text}] {label}: filtered {score(r['filtered'], s):.2f}° smoothed "
                  f"{score(r['smoothed'], s):.2f}° failed {r['counts']['failed_updates']} CPU {cpu:.1f} s", flush=True)
        t = s.t - s.t[0]
        for j, (a, b) in enumerate(cuts):
            t_end = t[b]
            t_stop = min(t_end + REC_MAX_S, t[cuts[j + 1][0]] if j + 1 < len(cuts) else t[-1])
            cells = []
            for w0, w1 in WINDOWS:
                sel = (t >= t_end + w0) & (t < min(t_end + w1, t_stop))
                cells.append(f"{w0}-{w1}s {_rms(err['drop'][sel]):6.2f}/{_rms(err['clean'][sel]):5.2f}")
            print(f"  drop at {t[a]:.2f} s (ends {t_end:.2f} s), filtered drop/clean: " + "  ".join(cells)
                  + f"  rec {recovery(err['drop'], err['clean'], t, t_end, t_stop)} s", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trials", nargs="?", default="06")
    ap.add_argument("--variant", action="append", default=None, help='StreamOptions "k=v;k=v" ("": default)')
    ap.add_argument("--drop-s", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    paths = trial_paths(a.trials)
    if not paths:
        return 2
    for p in paths:
        run(p, a.variant if a.variant is not None else [""], a.drop_s, a.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
