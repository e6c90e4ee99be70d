"""Task G (issue 3): the stream's tilt after a long sample drop — what holds the wrong solution, and options.

Streams one BROAD trial with the `stream_arrival` drops only (seeded, magnetometer at ¼ rate, as its `arrival`
run) through the default 2 s chain lag, with StreamOptions overrides (`--opt key=value`, repeatable), and prints
the filtered / smoothed RMS error (stream_arrival.score), and per gap_realign window its α*, σ_α and the tilt
of the predicted keyframe before / after the rotation by α* against opt_quat (scoring only: the estimator never
sees the truth). With `--trace T0,T1` it also prints, per keyframe in [T0, T1] (stream seconds from the trial
start), the keyframe's tilt error (angle between the estimated and the opt_quat "up" in the body frame:
heading-free), |v| and the gyro bias estimate.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/g3_tilt.py 06 [--drop-s 0.5] [--trace 121,130] \
        [--opt acc_huber_k=None] [--opt gap_realign_s=1.0 --opt gap_realign_keep=True]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.stream_arrival import BOOTSTRAP_S, arrivals, score, trial_paths  # noqa: E402
from benchmarks.common import load_broad_trial, stream_overrides  # noqa: E402
from imugraph.geometry import quat_to_rotmat  # noqa: E402
from imugraph.graphs.stream import StreamOptions  # noqa: E402
from imugraph.graphs.stream_run import bootstrap_calibration, session_smoother  # noqa: E402


def tilt_deg(nRb_est: np.ndarray, nRb_true: np.ndarray) -> float:
    """Angle between the body-frame up of two orientations: b_up = nRbᵀ e_z (heading-free)."""
    a, b = nRb_est.T[:, 2], nRb_true.T[:, 2]
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def realign_check(sm, s, row) -> str:
    """One gap_realign window, scored against opt_quat: the tilt of the predicted keyframe and of its rotation
    by α* about n̂ (stream_realign eq. R2) — the test is right when the second is the smaller."""
    k, alpha, sig, applied, R_pred = row
    t = sm._kf_t[k]
    R_true = quat_to_rotmat(s.quat[int(np.searchsorted(s.t, t))])
    n = np.asarray(sm.cal.n_mag, float)
    R_alpha = gtsam.Rot3.Expmap(np.radians(alpha) * n / np.linalg.norm(n)).matrix() @ R_pred
    return (f"t {t - s.t[0]:.1f} s α* {alpha:.1f}° σ_α {sig:.1f}° applied {int(applied)} tilt predicted "
            f"{tilt_deg(R_pred, R_true):.1f}° → realigned {tilt_deg(R_alpha, R_true):.1f}°")


def run(path: Path, seed: int, drop_s: float, overrides: dict, trace: tuple | None) -> dict:
    s = load_broad_trial(path)
    cal, n_boot = bootstrap_calibration(s, BOOTSTRAP_S)
    rng = np.random.default_rng(seed)
    mag4 = s.mag.copy()
    mag4[np.arange(s.n) % 4 != 0] = np.nan
    order, injected = arrivals(s.n, s.rate, n_boot, rng, frozenset({"drop"}), drop_s)
    opts = StreamOptions(**{"lag_s": 2.0, **overrides})
    sm = session_smoother(s, cal, n_boot, opts)
    if trace:
        print(f"velocity process: sigma_v {sm._sig_v:.3f} m/s, tau_v {sm._tau_v:.2f} s; g0 {sm._g:.3f}", flush=True)
    filtered = np.full((s.n, 4), np.nan)
    k_last = -1
    for i in order:
        q = sm.push_floats(float(s.t[i]), *s.gyr[i].tolist(), *s.acc[i].tolist(), *mag4[i].tolist())
        filtered[i] = q
        if trace and sm._k != k_last and sm._q_nk is not None:
            k_last = sm._k
            t_k = sm._kf_t[-1]
            if trace[0] <= t_k - s.t[0] <= trace[1]:
                j = int(np.searchsorted(s.t, t_k))
                R_est = quat_to_rotmat(np.array(sm._q_nk))
                R_true = quat_to_rotmat(s.quat[j])
                print(f"k {sm._k:5d} t {t_k - s.t[0]:8.2f} tilt {tilt_deg(R_est, R_true):7.2f}° "
                      f"|v| {np.linalg.norm(sm._v):6.2f} m/s  b_gyr {np.round(np.asarray(sm._b_gyr_est), 4)} rad/s", flush=True)
    sm.finish()
    kept = np.searchsorted(s.t, sm.sample_times())
    smoothed = np.full((s.n, 4), np.nan)
    smoothed[kept] = sm.smoothed()
    gaps_at = sorted({float(s.t[a] - s.t[0]) for a, b in zip(order[:-1], order[1:]) if b - a > 1})
    return {"filtered_deg": score(filtered, s), "smoothed_deg": score(smoothed, s),
            "failed": sm.stats.failed_updates, "gaps_at_s": gaps_at, "injected": injected,
            "realign": [realign_check(sm, s, r) for r in sm.realign_log],
            "update_cpu_p99_ms": 1e3 * float(np.percentile(np.asarray(sm.stats.update_cpu_s), 99))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trials", nargs="?", default="06")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drop-s", type=float, default=0.5)
    ap.add_argument("--opt", action="append", default=[], help="StreamOptions field=value (Python literal)")
    ap.add_argument("--trace", default=None, help="T0,T1: per-keyframe states in this stream-time range")
    a = ap.parse_args(argv)
    overrides = stream_overrides(a.opt)
    trace = None if a.trace is None else tuple(float(x) for x in a.trace.split(","))
    for p in trial_paths(a.trials):
        r = run(p, a.seed, a.drop_s, overrides, trace)
        print(f"trial {p.stem[:8]} drop {a.drop_s} s opts {overrides}: filtered {r['filtered_deg']:.2f}° "
              f"smoothed {r['smoothed_deg']:.2f}° failed {r['failed']} p99 update CPU {r['update_cpu_p99_ms']:.2f} ms "
              f"gaps at {[round(x, 2) for x in r['gaps_at_s']]} realign {r['realign']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
