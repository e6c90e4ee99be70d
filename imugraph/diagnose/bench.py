"""`imugraph bench diagnose`: the validation harness (imugraph.diagnose.harness) on real undisturbed BROAD
trials and on simulations; prints the confusion matrix and scores, writes harness.json and harness.md.

Sessions: the BROAD trials named by --trials (default the undisturbed rotation trials present in the data
folder: 01, 02, 04, 06, 07 — the translation trials hold real linear acceleration, an effect of the
library, so they are not "undisturbed" for the base model), each cropped to its --duration seconds with
the most movement (`most_moving`), plus --sims simulated sessions (random rotation, BROAD-like sensor:
285.714 Hz by default, gyro bias, noise, distorted magnetometer in µT).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

DEFAULT_TRIALS = ("01", "02", "04", "06", "07")


def simulated_session(seed: int, duration_s: float, rate_hz: float):
    """A BROAD-like simulated session: random rotation about all axes with two pauses, gyro bias 0.2 °/s,
    noise at BROAD's levels, field 44 µT with dip 69°, mildly distorted magnetometer."""
    from imugraph.sim.motion import random_rotation_motion
    from imugraph.sim.sensors import SensorParams, simulate_imu

    rng = np.random.default_rng(seed)
    motion = random_rotation_motion(duration_s, rate_hz, rng, rms_rate=1.0, pauses=2)
    params = SensorParams(gyro_bias=np.deg2rad(0.2) * rng.standard_normal(3), gyro_noise=0.004,
                          acc_noise=0.03, mag_noise=0.5, field_norm=44.0, dip_rad=np.deg2rad(69.0),
                          mag_D=np.eye(3) + 0.03 * rng.standard_normal((3, 3)),
                          mag_o=3.0 * rng.standard_normal(3))
    return simulate_imu(*motion, params, rng, name=f"sim{seed:02d}")


def most_moving(session, duration_s: float) -> tuple[int, int]:
    """Sample range [i0, i1) of the `duration_s` stretch with the largest mean angular rate |y_gyr − median|
    (starts on a 1 s grid): a crop with movement in it (BROAD 02's first 40 s hold none, so a gyro effect
    injected there is not observable, whatever the diagnoser does)."""
    t = session.t
    w = np.linalg.norm(np.nan_to_num(session.gyr - np.nanmedian(session.gyr, axis=0)), axis=1)
    c = np.concatenate([[0.0], np.cumsum(w)])
    best, span = (0, session.n), -1.0
    for t0 in np.arange(t[0], t[-1] - duration_s + 1e-9, 1.0):
        i0 = int(np.searchsorted(t, t0))
        i1 = int(np.searchsorted(t, t0 + duration_s))
        if c[i1] - c[i0] > span:
            best, span = (i0, i1), c[i1] - c[i0]
    return best


def broad_sessions(trials, duration_s: float | None, data_dir: str | None = None) -> list:
    """The named BROAD trials present in the data folder (.mat), cropped to `duration_s` (None: whole)."""
    from imugraph.config import broad_dir
    from imugraph.io.readers import load_session

    root = Path(data_dir) / "broad" if data_dir else broad_dir()
    out = []
    for tr in trials:
        hits = sorted(root.glob(f"{tr}_*.mat")) if root.is_dir() else []
        if not hits:
            continue
        s = load_session(hits[0])
        if duration_s is not None and s.t[-1] - s.t[0] > duration_s:
            s = s.slice(*most_moving(s, duration_s))
        out.append(s)
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `imugraph bench diagnose` (and of benchmarks/diagnose_harness.py)."""
    p.add_argument("--trials", default=",".join(DEFAULT_TRIALS),
                   help="BROAD trial numbers to inject into, comma separated (default 01,02,04,06,07; '' for none)")
    p.add_argument("--sims", type=int, default=2, help="simulated sessions to inject into (default 2)")
    p.add_argument("--n", type=int, default=2, help="injected cases per effect (default 2)")
    p.add_argument("--effects", default=None, help="effect names, comma separated (default: all)")
    p.add_argument("--duration", type=float, default=60.0, help="crop sessions to this many seconds (default 60)")
    p.add_argument("--rate", type=float, default=285.714, help="sampling rate of the simulations, Hz")
    p.add_argument("--seed", type=int, default=0, help="seed of the injections and simulations (default 0)")
    p.add_argument("--cases", default=None,
                   help="case ids to diagnose, comma separated (e.g. 013,020); the other cases are drawn but "
                        "skipped, so the selected ones are the same as in a full run (default: all)")
    p.add_argument("--hosts", choices=("random", "cycle"), default="random",
                   help="host of each injected case: drawn from the seed (random, default) or cycling "
                        "through the sessions in order (cycle: the pairing of earlier runs)")
    p.add_argument("--no-clean", action="store_true", help="skip the unmodified sessions (truth none)")
    p.add_argument("--out", default="bench_out/diagnose", help="folder for harness.json / harness.md")
    p.add_argument("--data-dir", default=None, help="data folder (default $IMUGRAPH_DATA, else ../shared/data)")
    p.add_argument("--quiet", action="store_true", help="no per-case lines on stderr")
    model_arguments(p)


# on/off switches of DiagnoseOptions, each --x-y the field x_y (None: the module's own default, stated in the help)
SWITCHES = [
    ("--timing-rules", "time_offset's rules T5–T7 (field remainder out, log-score significance, rotation "
                       "check; DiagnoseOptions.timing_rules; default on)"),
    ("--gyro-delay-model", "S15: time_offset's extended model of a gyro delay (T8)–(T10) (DiagnoseOptions."
                           "gyro_delay_model; default on)"),
    ("--magnet-ramps", "S15: magnetic_disturbance's field with fitted ramps at the window edges (R1) "
                       "(DiagnoseOptions.magnet_ramps; default on)"),
    ("--magnet-step-refit", "S16-E (M3'): magnetic_disturbance's step search repeated on the residual of the "
                            "(M1) fit of the windows found (DiagnoseOptions.magnet_step_refit; default on since "
                            "session 16)"),
    ("--saturation-censor", "S16-E (C1'): a gyro sample on a rail censored in saturation's residuals "
                            "(DiagnoseOptions.saturation_censor; default on since session 16)"),
    ("--saturation-area", "S16-E (C1''): the censored gyro values estimated per keyframe interval against the "
                          "keyframes (DiagnoseOptions.saturation_area; default off)"),
    ("--vibration-band-windows", "S16-F (V3)-(V4): vibration's windows re-localised on the fitted band, "
                                 "narrow-band excess only (DiagnoseOptions.vibration_band_windows; default on "
                                 "since session 16)"),
    ("--fold-fixed-structure", "S17-H (T11): cross-validation folds refit an effect with the discrete structure "
                               "of its all-sample fit held (time_offset's channel; DiagnoseOptions."
                               "fold_fixed_structure; default on since session 17)"),
    ("--local-check", "S17-H (V'): a localised verdict leaves when a global effect on its channel explains its "
                      "support at least as well by the held-out log score (DiagnoseOptions.local_check; "
                      "default off)"),
    ("--magnet-intermittent", "S20-M (M6): magnetic_disturbance's windows for an intermittent disturbance (a "
                              "stationary magnet visited several times; DiagnoseOptions.magnet_intermittent; "
                              "default off)"),
    ("--magnet-visit-drift", "S20-M (M7): magnetic_disturbance's window field drifting through the window "
                             "(DiagnoseOptions.magnet_visit_drift; default off)"),
    ("--vibration-motion-check", "S20-V (V6): vibration relevant only beyond the band RMS the measured angular "
                                 "motion explains at a hand's lever arm (DiagnoseOptions.vibration_motion_check; "
                                 "default on since session 20)"),
    ("--timing-confidence", "S20-V (T12): time_offset relevant only when |τ| ≥ 1 sample + 1.645 × its folds' "
                            "jackknife SE (DiagnoseOptions.timing_confidence; default on since session 20)"),
    ("--refit-hold-noise", "S20-Mb: the full refit's (F1) rounds hold the base fit's noise levels instead of "
                           "re-estimating them (DiagnoseOptions.refit_hold_noise; default off)"),
    ("--refit-accelerate", "S20-Mb (F2): the full refit's alternation extrapolated to its fixed point "
                           "(Aitken, after 4 rounds; DiagnoseOptions.refit_accelerate; default off)"),
    ("--nested-check", "S20-W (V''): an effect named by the log-score route must keep its held-out log score "
                       "on top of a stronger relevant effect on its channel (DiagnoseOptions.nested_check; "
                       "default off)"),
    ("--shift-prediction", "S20-W (T13): time_offset's acc/mag residual y − h(t − τ), the prediction shifted, not "
                           "the data interpolated (DiagnoseOptions.shift_prediction; default off)"),
    ("--whitening-jacobian", "S20-W (L3): the log score of a whitened residual (linear_acceleration, vibration) "
                             "charged its filter's Jacobian (DiagnoseOptions.whitening_jacobian; default off)"),
    ("--timestamp-jitter", "S20-T: the timestamp_jitter effect (host receive stamps re-timed on a fitted sample "
                           "clock) in the library (DiagnoseOptions.timestamp_jitter; default on since session 20)"),
]


def model_arguments(p: argparse.ArgumentParser) -> None:
    """The diagnosis' model switches (read back by `diagnose_options`)."""
    p.add_argument("--joint-gyro", action=argparse.BooleanOptionalAction, default=None,
                   help="gyro effects fitted jointly with the trajectory (DiagnoseOptions.joint_gyro; default on)")
    p.add_argument("--subsample-lag", action=argparse.BooleanOptionalAction, default=None,
                   help="the magnetometer's sub-sample lag in the base model (DiagnoseOptions.subsample_lag)")
    p.add_argument("--score", choices=("cost", "logscore", "gap"), default="cost",
                   help="significance of a jointly fitted gyro effect: its own objective on held-out rows "
                        "(cost, default), the held-out log score of the two joint solutions (logscore), or "
                        "the held-out gap (A2) as before (gap)")
    p.add_argument("--joint-refit", action=argparse.BooleanOptionalAction, default=None,
                   help="stage-2 alternation for a jointly fitted gyro effect (AttributionOptions.joint_refit; "
                        "default off)")
    for flag, text in SWITCHES:
        p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=text)
    p.add_argument("--cross-gap", type=float, default=None, metavar="W",
                   help="S16: weight w_x of the gap's cross-channel term (G1'), the correlation of the acc and "
                        "mag residuals with the model's motion derivative (GapOptions.cross_weight; default 0: off)")
    p.add_argument("--cross-form", choices=("corr", "cov"), default=None,
                   help="S16: the cross-channel term as a correlation (G4) or a covariance in whitened units (G4') "
                        "(GapOptions.cross_form; default corr)")
    p.add_argument("--drift-basis", choices=("legendre", "spline"), default=None,
                   help="gyro_bias_drift's basis (DiagnoseOptions.drift_basis; default legendre)")


def diagnose_options(args: argparse.Namespace, **fields):
    """DiagnoseOptions(**fields) with the model switches of `model_arguments`."""
    from dataclasses import replace

    from imugraph.diagnose.run import DiagnoseOptions

    switches = {n: getattr(args, n, None) for n in (flag[2:].replace("-", "_") for flag, _ in SWITCHES)}
    o = DiagnoseOptions(joint_gyro=getattr(args, "joint_gyro", None),
                        subsample_lag=getattr(args, "subsample_lag", None),
                        drift_basis=getattr(args, "drift_basis", None), **switches, **fields)   # None: the defaults
    if getattr(args, "cross_gap", None) is not None:                        # S16 (G1')
        o = replace(o, gap=replace(o.gap, cross_weight=float(args.cross_gap)))
    if getattr(args, "cross_form", None) is not None:
        o = replace(o, gap=replace(o.gap, cross_form=str(args.cross_form)))
    score = getattr(args, "score", "cost") or "cost"
    att = replace(o.attribution, own_score="" if score == "gap" else score)
    if getattr(args, "joint_refit", None) is not None:
        att = replace(att, joint_refit=bool(args.joint_refit))
    return replace(o, attribution=att)


def diagnose_function(args: argparse.Namespace):
    """session → Diagnosis with the model switches of `add_arguments` (DiagnoseOptions)."""
    from imugraph.diagnose.run import diagnose

    o = diagnose_options(args)
    return lambda session: diagnose(session, o)


def harness_sessions(args: argparse.Namespace) -> list:
    """The harness's host sessions from `add_arguments`' options: the BROAD trials (--trials, --duration) then
    --sims simulated ones seeded seed·100 + i (may be empty)."""
    trials = [t.strip() for t in (getattr(args, "trials", "") or "").split(",") if t.strip()]
    duration = getattr(args, "duration", None)
    sessions = broad_sessions(trials, duration, getattr(args, "data_dir", None))
    seed = int(getattr(args, "seed", 0) or 0)
    sessions += [simulated_session(seed * 100 + i, duration or 60.0, float(getattr(args, "rate", 285.714)))
                 for i in range(int(getattr(args, "sims", 0) or 0))]
    return sessions


def harness_run(args: argparse.Namespace, sessions: list, diagnose_fn, progress=None) -> dict:
    """`harness.run_harness` over `sessions` with `add_arguments`' --effects, --n, --seed, --no-clean, --cases
    and --hosts, diagnosing with diagnose_fn; progress: optional callable(str) (a header line, then one per case)."""
    from imugraph.diagnose.effects import EFFECTS
    from imugraph.diagnose.harness import run_harness
    from imugraph.diagnose.run import load_effects, model_switches
    from imugraph.errors import SessionError

    names = getattr(args, "effects", None)
    if names:
        names = [n.strip() for n in names.split(",") if n.strip()]
    else:                                     # the library the diagnoses will use (--no-timestamp-jitter drops it)
        with model_switches(diagnose_options(args)):
            names = list(load_effects())
    bad = [n for n in names if n not in EFFECTS]
    if bad:
        raise SessionError("--effects", "effects", ", ".join(bad), f"names among {sorted(EFFECTS)}")
    if progress is not None:
        progress(f"harness: {len(sessions)} sessions ({', '.join(s.name for s in sessions)}), "
                 f"{len(names)} effects × {args.n}")
    return run_harness(sessions, names, int(args.n), np.random.default_rng(int(getattr(args, "seed", 0) or 0)),
                       clean=not getattr(args, "no_clean", False), progress=progress, diagnose_fn=diagnose_fn,
                       only=[c.strip() for c in args.cases.split(",") if c.strip()]
                       if getattr(args, "cases", None) else None,
                       hosts=getattr(args, "hosts", "random") or "random")


def run_bench_diagnose(args: argparse.Namespace) -> int:
    """Run the harness with the options of `add_arguments`; returns 0 (errors raise ImugraphError)."""
    import json
    import sys

    from imugraph.diagnose.harness import format_report
    from imugraph.errors import SessionError
    from imugraph.io.writers import atomic_write_text, json_ready

    sessions = harness_sessions(args)
    if not sessions:
        raise SessionError("--trials/--sims", "sessions", "no BROAD trial found and --sims 0",
                           "at least one session")
    quiet = bool(getattr(args, "quiet", False))
    say = (lambda m: None) if quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    report = harness_run(args, sessions, diagnose_function(args), say)
    text = format_report(report)
    print(text)
    out = Path(getattr(args, "out", "bench_out/diagnose"))
    atomic_write_text(out / "harness.json", json.dumps(json_ready(report), indent=1))
    atomic_write_text(out / "harness.md", "# Diagnosis harness\n\n```\n" + text + "\n```\n")
    say(f"wrote {out / 'harness.json'} and {out / 'harness.md'}")
    return 0
