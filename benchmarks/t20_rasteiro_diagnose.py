"""Benchmark T20 (issue 5, docs/diagnose.md §S20-T): the gyro gap of the Rasteiro recordings is their PC-receive
timestamps — measured against the robot, and the diagnosis with and without the timestamp_jitter effect.

Per Rasteiro raw-sensor file (3 sequences × the 4 raw sensors):
  clock   the fitted sample clock (imugraph/diagnose/sample_clock.py (J1)–(J3), chosen among the candidates by (J7),
          the candidates printed first): period, lost samples, phase lock (J5), the stamps'
          deviation t − τ (robust RMS in sample periods = the effect's size; 99th percentile in ms);
  robot   the gyro integrated over windows of `--window` samples on the STAMPS (Δt) and on the CLOCK (Δτ),
          against the robot's rotation over the same span (ABBquaternion; truth interpolated in PC time at
          each model's window ends, each model at its own best lag within ±0.3 s; gyro bias = median at the
          robot's rest): RMS angle error, degrees, over windows where the robot turns ≥ 1°;
  close   the base fit's keyframe closing error ε_k = Σ_{j∈k} r_gyr,j Δt_j (the rotation by which the
          integrated gyro misses the next keyframe, (R1)), RMS in degrees, for the recording on its stamps and
          re-timed on its clock, each beside its simulation A (fit_simulation of simulate_from_fit, seed 0);
  control a simulation from the re-timed fit (truth on the clock, seed 1) fitted on its clock and again with the
          recording's own stamps put on its samples: closing-error RMS and whitened gyro residual RMS — what
          these stamps alone do to an otherwise exact recording;
  diag    `imugraph diagnose` without the effect (--no-timestamp-jitter; the default before session 20) and with it: per
          channel the raw gap and the noise floor, the verdict, and timestamp_jitter's stage, (A1) shrink,
          (A2), significance, size; `only` = the effect alone (its refit is otherwise skipped when a localised
          verdict is found, (V)); `retimed` = the gap of the recording re-timed on its clock (the gap the
          gyro would leave if the stamps were the clock's).

Truth is used only to score (the robot line); the diagnosis never sees it.

    .venv/bin/python benchmarks/t20_rasteiro_diagnose.py [--files V_300/Sequencia1/MPU9150,...] [--window 20]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SEQS = ("V_300/Sequencia1", "V1000/Sequencia3", "eV50p/Sequencia1")
SENSORS = ("MPU9150", "LSM9DS0", "MPU6050RM3100", "MPU6500RM3100")


def _slerp_at(t_known: np.ndarray, R: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations at t_query interpolated (geodesic) between the known samples (ends held)."""
    from imugraph.geometry import expmap, logmap

    i = np.clip(np.searchsorted(t_known, t_query) - 1, 0, len(t_known) - 2)
    span = np.maximum(t_known[i + 1] - t_known[i], 1e-12)
    u = np.clip((t_query - t_known[i]) / span, 0.0, 1.0)
    rel = logmap(np.transpose(R[i], (0, 2, 1)) @ R[i + 1])
    return R[i] @ expmap(u[:, None] * rel)


def robot_window_error(s, times: np.ndarray, window: int, lags=np.arange(-0.3, 0.3001, 0.005)) -> tuple:
    """RMS angle error (deg) of the gyro's rotation over non-overlapping windows of `window` samples, the
    samples placed at `times` (the steps Δ = diff(times)), against the robot's rotation between the window
    ends' times + lag, at the best lag; windows where the robot turns ≥ 1°. Returns (rms, lag, windows)."""
    from imugraph.geometry import expmap, logmap, quat_to_rotmat

    nRb = quat_to_rotmat(s.quat)
    w_robot = np.linalg.norm(logmap(np.transpose(nRb[:-1], (0, 2, 1)) @ nRb[1:]), axis=1) / np.diff(s.t)
    rest = np.r_[w_robot < 0.01, False]
    b = np.median(s.gyr[rest], axis=0) if rest.sum() > 20 else np.zeros(3)
    step = np.diff(times)
    inc = expmap((s.gyr[:-1] - b) * step[:, None])
    starts = np.arange(0, s.n - window - 1, window)
    Rg = []
    for a in starts:                                         # gyro rotation over [a, a + window]
        R = np.eye(3)
        for j in range(a, a + window):
            R = R @ inc[j]
        Rg.append(R)
    Rg = np.array(Rg)
    best = (np.inf, 0.0, 0)
    for lag in lags:
        Ra = _slerp_at(s.t, nRb, times[starts] + lag)
        Rb = _slerp_at(s.t, nRb, times[starts + window] + lag)
        Rt = np.transpose(Ra, (0, 2, 1)) @ Rb
        moving = np.degrees(np.linalg.norm(logmap(Rt), axis=1)) >= 1.0
        if moving.sum() < 10:
            continue
        err = np.degrees(np.linalg.norm(logmap(np.transpose(Rg[moving], (0, 2, 1)) @ Rt[moving]), axis=1))
        rms = float(np.sqrt(np.mean(err**2)))
        if rms < best[0]:
            best = (rms, float(lag), int(moving.sum()))
    return best


def whitened_rms(fit) -> float:
    z = fit.residuals["gyr"] / fit.sigma["gyr"]
    return float(np.sqrt(np.nanmean(z**2)))


def _gaps(d) -> str:
    return " ".join(f"{c} {d.gap_raw[c]:.2f}/{d.null_gap[c]:.2f}" for c in ("gyr", "acc", "mag"))


def _jitter(d) -> str:
    r = next((r for r in d.effects if r.name == "timestamp_jitter"), None)
    if r is None:
        return "-"
    sz = r.size or {}
    return (f"{r.stage} shrink {r.shrink:.2f} (A2) {r.penalised:+.2f} sig {int(bool(r.significant))} "
            f"size {sz.get('value', np.nan):.2f}/{sz.get('threshold', np.nan):.2f}")


def main(argv=None) -> int:
    from imugraph.config import data_dir
    from imugraph.diagnose.effects import timestamp_jitter as tj
    from imugraph.diagnose.fit import base_options, fit_base, fit_simulation, simulate_from_fit
    from imugraph.io.session import Session
    from imugraph.diagnose.run import DiagnoseOptions, diagnose
    from imugraph.errors import ImugraphError
    from imugraph.io.readers import load_session

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--files", default=None, help="SEQ/SENSOR list, comma separated (default: all 12)")
    p.add_argument("--window", type=int, default=20, help="samples per robot-scored window (default 20 ≈ 0.2 s)")
    p.add_argument("--no-diagnose", action="store_true", help="clock and robot evidence only")
    args = p.parse_args(argv)
    root = Path(data_dir()) / "rasteiro" / "DataSets"
    files = (args.files.split(",") if args.files else [f"{q}/{s}" for q in SEQS for s in SENSORS])
    for name in files:
        path = root / f"{name}.mat"
        try:
            s = load_session(path)
        except (ImugraphError, OSError) as exc:
            print(f"{name}: not loaded ({exc})")
            continue
        c0 = time.process_time()
        fit0 = fit_base(s, base_options())
        _, info = tj.EFFECT.refit(fit0)             # (J7): the clock the effect chooses among the candidates
        clock = tj.clock_of(s.t, s.gyr)
        print(f"{name}: clock candidates (J3 cost, robust spread in samples (J7'), re-timed closing error ε (J7)): " + " | ".join(
            f"{1e3 * c['period_s']:.3f} ms lost {c['lost']} cost {c['cost_J3']:.3f} spread {c['spread_samples']:.2f} ε {c['closing_deg']:.3f}°"
            for c in info["candidates"]))
        dev = clock["deviation"]
        rob = 1.4826 * np.median(np.abs(dev - np.median(dev))) / clock["period"]
        print(f"{name}: n {s.n} | clock period {1e3 * clock['period']:.3f} ms lost {clock['lost']} lock {clock['lock']:.1f} | stamps − clock "
              f"robust RMS {rob:.2f} samples, p99 {1e3 * np.quantile(dev - np.median(dev), 0.99):.0f} ms")
        e_t = robot_window_error(s, s.t, args.window)
        e_c = robot_window_error(s, clock["tau"], args.window)
        print(f"  robot: {args.window}-sample gyro rotation error RMS stamps {e_t[0]:.3f}° (lag {e_t[1]:+.3f} s, "
              f"{e_t[2]} windows) | clock {e_c[0]:.3f}° (lag {e_c[1]:+.3f} s, {e_c[2]} windows)")
        s_r = tj.retimed(s, clock)
        fits = {}
        for tag, ss in (("stamps", s), ("clock", s_r)):
            f = fit_base(ss, base_options())
            fits[tag] = (f, fit_simulation(simulate_from_fit(f, np.random.default_rng(0)), f))
        print("  close: ε RMS " + " | ".join(f"{tag} real {tj.closing_error_deg(f):.3f}° sim {tj.closing_error_deg(fs):.3f}°"
                                             for tag, (f, fs) in fits.items())
              + f"; σ_ω per sample {np.round(fits['stamps'][0].calibration.noise['gyr'], 5).tolist()} rad/s, "
                f"whitening σ_ω/√M {np.round(fits['stamps'][0].sigma['gyr'], 5).tolist()}")
        sim_c = simulate_from_fit(fits["clock"][0], np.random.default_rng(1))
        sim_t = Session(t=s.t.copy(), gyr=sim_c.gyr, acc=sim_c.acc, mag=sim_c.mag, quat=sim_c.quat,
                        source=sim_c.source, name=sim_c.name + "_on_stamps", meta=dict(sim_c.meta))
        ctl = {tag: fit_base(ss, base_options()) for tag, ss in (("clock", sim_c), ("stamps", sim_t))}
        print("  control: simulation (truth on the clock) " + " | ".join(
            f"on {tag}: ε RMS {tj.closing_error_deg(f):.3f}°, whitened gyro RMS {whitened_rms(f):.1f}"
            for tag, f in ctl.items()))
        if not args.no_diagnose:
            d0 = diagnose(s, DiagnoseOptions(timestamp_jitter=False))
            d1 = diagnose(s, DiagnoseOptions(timestamp_jitter=True))
            d2 = diagnose(s, DiagnoseOptions(effects=("timestamp_jitter",)))
            d3 = diagnose(tj.retimed(s, clock), DiagnoseOptions())
            print(f"  diag -jitter : {_gaps(d0)} | verdict {d0.verdict}")
            print(f"  diag +jitter : {_gaps(d1)} | verdict {d1.verdict} | timestamp_jitter {_jitter(d1)}")
            print(f"  diag only    : verdict {d2.verdict} | timestamp_jitter {_jitter(d2)}")
            print(f"  diag retimed : {_gaps(d3)} | verdict {d3.verdict}")
            d4 = diagnose(sim_t, DiagnoseOptions(effects=("timestamp_jitter",)))
            print(f"  diag control on stamps: {_gaps(d4)} | verdict {d4.verdict} | timestamp_jitter {_jitter(d4)}")
        print(f"  cpu {time.process_time() - c0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
