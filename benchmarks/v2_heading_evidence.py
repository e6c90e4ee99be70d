"""Where the heading error of the fast-translation BROAD trials comes from (evidence before modelling).

For each selected trial: total / inclination / heading RMS error of imugraph with today's defaults and with
one element switched off or changed at a time (the `VARIANTS` below), offline VQF beside them, and the
autocorrelation of the optical velocity (opt_pos differentiated; evaluation only, never fed to an estimate)
at lags of 0.05–0.6 s; for today's defaults and offline VQF, the share of the heading error's power (the
nav-z component of the scored error after the best shift and heading offset) below 0.2 Hz (slower than 5 s).

    .venv/bin/python benchmarks/v2_heading_evidence.py [TRIAL_NUMBERS,...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, iter_broad, parse_options  # noqa: E402
from benchmarks.peers import vqf_offline  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.evaluate import _align  # noqa: E402  (the scorer's alignment, to see the error over time)

VARIANTS = {
    "default": [],
    "no_field_perturbation": ["field_sigma=None"],
    "process_off": ["estimate_velocity_process='off'"],
    "acc_as_noise": ["linear_acceleration='noise'"],
    "no_windows": ["disturbance_windows=False"],
    "bias_seg_20s": ["bias_segment_s=20.0"],
    "correlated_noise": ["correlated_noise=True"],
    "ar2_free": ["estimate_velocity_process='free_ar2'"],
}
LAGS_S = (0.05, 0.1, 0.2, 0.3, 0.4, 0.6)


def optical_autocorrelation(pos: np.ndarray, rate: float) -> dict:
    """ρ(lag) of the optical velocity (central difference over ±0.05 s, pooled over axes, finite pairs)."""
    h = max(1, int(round(0.05 * rate)))
    v = (pos[2 * h:] - pos[:-2 * h]) / (2 * h / rate)
    v = v - np.nanmean(v, axis=0)
    out = {}
    for lag in LAGS_S:
        m = int(round(lag * rate))
        a, b = v[:-m], v[m:]
        ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
        out[lag] = round(float(np.sum(a[ok] * b[ok]) / np.sqrt(np.sum(a[ok] ** 2) * np.sum(b[ok] ** 2))), 3)
    return out


def slow_heading_share(q: np.ndarray, s, mask, rate: float) -> float:
    """Fraction of the power of the heading-error series (nav z of the aligned error) below 0.2 Hz."""
    w, _, _, z = _align(q, s.quat, mask, 3.0, 0.25, True).q_err
    h = 2 * np.arctan2(z * np.sign(w), np.abs(w))
    f = np.fft.rfftfreq(len(h), 1 / rate)
    P = np.abs(np.fft.rfft(h - h.mean())) ** 2
    return float(P[f < 0.2].sum() / P.sum())


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=(), max_args=1)
    from scipy.io import loadmat

    select = set(argv[0].split(",")) if argv else {"15", "16"}
    check_trials(select)
    for num, s, mask in iter_broad(select):
        pos = np.asarray(loadmat(s.source)["opt_pos"], float)
        print(f"trial {num}: optical velocity autocorrelation {optical_autocorrelation(pos, s.rate)}")
        q_vqf = vqf_offline(s)
        tot, inc, hdg = error_parts(q_vqf, s, mask)
        print(f"  {'offline_vqf':24s} total {tot:.3f}  incl {inc:.3f}  heading {hdg:.3f}  "
              f"heading power < 0.2 Hz {slow_heading_share(q_vqf, s, mask, s.rate):.2f}")
        for name, opts in VARIANTS.items():
            est = calibrate(s, parse_options(opts), allow_weak=True)
            tot, inc, hdg = error_parts(est.quat, s, mask)
            slow = f"  heading power < 0.2 Hz {slow_heading_share(est.quat, s, mask, s.rate):.2f}" if not opts else ""
            print(f"  {name:24s} total {tot:.3f}  incl {inc:.3f}  heading {hdg:.3f}{slow}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
