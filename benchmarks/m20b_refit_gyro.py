"""Benchmark (issue 5, S20-Mb): why the full refit (F1) of an effect changes the GYRO fit away from the effect.

For each BROAD trial: the base fit F0 (as `imugraph diagnose` makes it), then refits θ of the base model
on data that differ from the recording only where an effect was removed, and per refit the whitened gyro
residual RMS (R1) with the base σ (what the gap and the log score see) on the effect's support (its windows
± 1 s; the whole recording for a global effect) and outside it, beside the fitted noise levels σ_acc, σ_mag
and the gyro bias:

    null      fit_simulation(y, F0): the refit machinery on the UNCHANGED recording (a control: any change
              here is the machinery's, not the effect's)
    round r   the effect's alternation (refit.refit_effect / MagneticDisturbance.refit) step by step
    held-σ    the last round's corrected data refitted with the noise levels held (refit.HOLD_NOISE)
    θ*        the diagnosis' own refit (rounds 2), default (F1) and with refit.ACCELERATE (F2); for
              magnetic_disturbance with the gyro part of the held-out log score (A4) on its support per fold

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20b_refit_gyro.py --trials 28 --effects magnetic_disturbance
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20b_refit_gyro.py --trials 15 --effects linear_acceleration
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20b_refit_gyro.py --sim --trials ''
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.common import select_trials  # noqa: E402


def rms(fit, c: str, sg: np.ndarray, m: np.ndarray) -> float:
    """Whitened RMS of channel c's residual (R1)–(R3) with the base fit's σ over the samples m."""
    return float(np.sqrt(np.nanmean((fit.residuals[c][m] / sg) ** 2))) if m.any() else float("nan")


def line(label: str, fit, real, sup: np.ndarray) -> str:
    s = {c: np.asarray(real.sigma[c], float) for c in ("gyr", "acc", "mag")}
    n = fit.calibration.noise
    every = np.ones(real.n, bool)
    return (f"    {label:<22} gyro RMS all {rms(fit, 'gyr', s['gyr'], every):6.1f}  support "
            f"{rms(fit, 'gyr', s['gyr'], sup):6.1f}  outside {rms(fit, 'gyr', s['gyr'], ~sup):6.1f} | acc, mag RMS "
            f"outside {rms(fit, 'acc', s['acc'], ~sup):.2f}, {rms(fit, 'mag', s['mag'], ~sup):.2f} | σ_gyr "
            f"{np.round(np.asarray(n['gyr']) * 1e3, 3).tolist()} mrad/s σ_acc {np.round(n['acc'], 3).tolist()} "
            f"σ_mag {np.round(n['mag'], 3).tolist()} | bias {np.round(np.asarray(fit.calibration.gyro_bias) * 1e3, 3).tolist()}"
            f" mrad/s | iters {fit.info.get('iterations')}")


def where(real, ext, sup: np.ndarray, block_s: float = 2.0, top: int = 6) -> None:
    """Where outside the support the last round's whitened gyro Σ r² grew: the blocks of block_s with the
    largest growth and the share of the total growth they carry."""
    t = real.session.t
    z0 = np.nansum((real.residuals["gyr"] / real.sigma["gyr"]) ** 2, axis=1)
    z1 = np.nansum((ext.residuals["gyr"] / real.sigma["gyr"]) ** 2, axis=1)
    b = ((t - t[0]) // block_s).astype(int)
    grow = np.bincount(b[~sup], (z1 - z0)[~sup], minlength=b.max() + 1)
    total = float(grow.sum())
    idx = np.argsort(-grow)[:top]
    print(f"    growth of Σ gyro z² outside the support: {total:.3g}; largest {block_s:.0f} s blocks: "
          + ", ".join(f"{t[0] + k * block_s:.0f}–{t[0] + (k + 1) * block_s:.0f} s {grow[k] / total:.0%}" for k in idx)
          + f" (together {grow[idx].sum() / total:.0%}; blocks with growth > 0: {(grow > 0).sum()} of "
            f"{len(np.unique(b[~sup]))})", flush=True)


def support_of(effect, real, corr) -> np.ndarray:
    from imugraph.diagnose.effects.base import window_mask

    wins = [(w["t_start"] - 1.0, w["t_end"] + 1.0) for w in (corr.params or {}).get("windows", [])]
    return window_mask(real.session.t, wins) if wins else np.zeros(real.n, bool)


def study(session, name: str) -> None:
    from imugraph.diagnose import refit as rf
    from imugraph.diagnose.effects import EFFECTS
    from imugraph.diagnose.effects import magnetic_disturbance as md
    from imugraph.diagnose.effects.base import replace_session
    from imugraph.diagnose.fit import base_options, fit_base, fit_simulation

    c0 = time.process_time()
    real = fit_base(session, base_options(5.0))
    effect = md._ALTERNATION if name == "magnetic_disturbance" else EFFECTS[name]
    train = np.ones(real.n, bool)
    corr0 = effect.fit(real, train)
    sup = support_of(effect, real, corr0)
    print(f"  {name}: support (windows ± 1 s) {sup.mean():.2f} of the recording", flush=True)
    print(line("base F0", real, real, sup), flush=True)
    null = rf.on_session(fit_simulation(real.session, real), real.session)
    print(line("null refit (y as is)", null, real, sup), flush=True)
    cur, new = real, None
    for r in (1, 2):
        view = real if cur is real else rf.on_session(cur, real.session)
        corr = effect.fit(view, train)
        new = corr.corrected(view) if hasattr(corr, "corrected") else {}
        if not new:
            print(f"    round {r}: nothing corrected")
            break
        cur = fit_simulation(replace_session(real.session, **new), cur)
        print(line(f"round {r}", rf.on_session(cur, real.session), real, sup), flush=True)
    if cur is not real:
        where(real, rf.on_session(cur, real.session), sup)
    if new:
        saved = rf.HOLD_NOISE
        try:
            rf.HOLD_NOISE = True
            held = fit_simulation(replace_session(real.session, **new), real, options=rf.refit_options(real))
        finally:
            rf.HOLD_NOISE = saved
        print(line("last data, held σ", rf.on_session(held, real.session), real, sup), flush=True)
    for acc in (False, True):                  # the diagnosis' own refit, default and (F2) refit.ACCELERATE
        saved = rf.ACCELERATE
        try:
            rf.ACCELERATE = acc
            ext, info = (md.EFFECT.refit if name == "magnetic_disturbance" else
                         (lambda *a: rf.refit_effect(effect, *a)))(real, 2)
        finally:
            rf.ACCELERATE = saved
        label = f"θ* (F2) ρ {info.get('rho', float('nan')):.2f}" if acc else "θ* default (F1)"
        print(line(label + f", {len(info['rounds'])} r", ext, real, sup), flush=True)
        if name == "magnetic_disturbance":
            folds_on_support(real, ext, md.EFFECT.fit(ext, np.ones(real.n, bool), window=info["window"]))
    print(f"    CPU {time.process_time() - c0:.0f} s", flush=True)


def folds_on_support(real, ext, full) -> None:
    """The diagnosis' own refit θ* (MagneticDisturbance.refit, the options' flags as set) and, per fold, the
    gyro part of the held-out log score (A4) on the effect's support (score.channel_scores with the support's
    training / held-out rows, as attribute.evaluate_effect forms it), split by where the rows are: the
    samples within PAD_S of a window edge (their magnetometer left out of θ*'s data by FieldRemoved) or not."""
    from imugraph.diagnose.attribute import AttributionOptions, fold_masks
    from imugraph.diagnose.effects import magnetic_disturbance as md
    from imugraph.diagnose.effects.base import window_mask
    from imugraph.diagnose.score import _axis_sigma, channel_scores
    from imugraph.diagnose.support import effect_support

    support = effect_support(full, real.session.t)
    if support is None:
        print("    θ*: no window")
        return
    t = real.session.t
    wins = full.params["windows"]
    edge = window_mask(t, [(w[k] - md.PAD_S, w[k] + md.PAD_S) for w in wins for k in ("t_start", "t_end")])
    sg = np.asarray(real.sigma["gyr"], float)
    rb, re = real.residuals["gyr"], ext.residuals["gyr"]
    print(f"    θ* windows {', '.join(f'{w[0]:.1f}–{w[1]:.1f}' for w in [(w['t_start'], w['t_end']) for w in wins])}; "
          f"gyro RMS (base σ) base → θ*: support edges (± {md.PAD_S:.0f} s, mag left out) "
          f"{rms(real, 'gyr', sg, support & edge):.1f} → {rms(ext, 'gyr', sg, support & edge):.1f}, support interior "
          f"{rms(real, 'gyr', sg, support & ~edge):.1f} → {rms(ext, 'gyr', sg, support & ~edge):.1f}")
    total, n_all = 0.0, 0
    for k, f in enumerate(fold_masks(t, AttributionOptions())):
        tr, te = ~f & support, f & support
        lb, le, n = channel_scores(rb, re, tr, te)
        if not n:
            continue
        ok = np.all(np.isfinite(rb), 1) & np.all(np.isfinite(re), 1)
        sb, se = _axis_sigma(rb, tr & ok) / sg, _axis_sigma(re, tr & ok) / sg
        total += lb - le
        n_all += n
        print(f"      fold {k}: gyro Δℓ {(lb - le) / n:+8.2f} nats/sample | train rows {int((tr & ok).sum())} "
              f"({(tr & ok & edge).sum() / max((tr & ok).sum(), 1):.0%} on edges), test rows {n} "
              f"({(te & ok & edge).sum() / n:.0%} on edges) | σ/σ_base on train: base {np.round(sb, 1).tolist()} "
              f"θ* {np.round(se, 1).tolist()} | test RMS/σ_base: base {rms(real, 'gyr', sg, te & ok):.1f} "
              f"θ* {rms(ext, 'gyr', sg, te & ok):.1f}")
    print(f"      gyro Δℓ on the support, all folds: {total / max(n_all, 1):+.2f} nats/sample", flush=True)


def simulated(seed: int = 7) -> None:
    """The simulation of tests/test_diagnose_refit_gyro.py (40 s, 100 Hz, a 0.5 |m| body-frame field over
    15–25 s): gyro whitened RMS (base σ) of the refit of the CLEAN data (the target: the field removed exactly),
    of the alternation after r rounds with no early stop (CONVERGED 0), of the default refit and of (F2)."""
    from imugraph.diagnose import refit as rf
    from imugraph.diagnose.bench import simulated_session
    from imugraph.diagnose.effects import magnetic_disturbance as md
    from imugraph.diagnose.effects.base import envelope, replace_session
    from imugraph.diagnose.fit import base_options, fit_base, fit_simulation

    s = simulated_session(seed, 40.0, 100.0)
    F = float(np.nanmedian(np.linalg.norm(s.mag, axis=1)))
    t0 = float(s.t[0])
    d = np.array([0.6, -0.5, 0.6]) / np.linalg.norm([0.6, -0.5, 0.6])
    real = fit_base(replace_session(s, mag=s.mag + envelope(s.t, (t0 + 15.0, t0 + 25.0), 0.3)[:, None] * (0.5 * F * d)),
                    base_options(5.0))
    sg = np.asarray(real.sigma["gyr"], float)
    g = lambda f: rms(f, "gyr", sg, np.ones(real.n, bool))  # noqa: E731
    b = lambda f: np.round(np.asarray(f.calibration.gyro_bias) * 1e3, 2).tolist()  # noqa: E731
    clean = rf.on_session(fit_simulation(s, real), real.session)
    print(f"simulation seed {seed}: gyro RMS base {g(real):.2f}; clean-data refit {g(clean):.2f} (bias {b(clean)} mrad/s)")
    saved = (rf.CONVERGED, rf.ACCELERATE, rf.ACCEL_ROUNDS)
    try:
        rf.CONVERGED = 0.0
        for r in (1, 2, 4, 8, 16):
            ext, _ = md.EFFECT.refit(real, r)
            print(f"  alternation, {r:2d} rounds (no early stop): {g(ext):.2f} (bias {b(ext)})")
        rf.CONVERGED = saved[0]
        ext, info = md.EFFECT.refit(real, 2)
        print(f"  default refit: {g(ext):.2f} ({len(info['rounds'])} rounds)")
        rf.ACCELERATE = True
        for k in (3, 4, 5):
            rf.ACCEL_ROUNDS = k
            ext, info = md.EFFECT.refit(real, 2)
            print(f"  (F2) {k} rounds + Aitken jump (ρ {info.get('rho', float('nan')):.2f}): {g(ext):.2f} (bias {b(ext)})")
    finally:
        rf.CONVERGED, rf.ACCELERATE, rf.ACCEL_ROUNDS = saved


def main(argv=None) -> int:
    from imugraph.io.readers import load_session

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default="28", help="BROAD trial numbers, comma separated (default 28)")
    p.add_argument("--effects", default="magnetic_disturbance", help="effect names, comma separated")
    p.add_argument("--sim", action="store_true", help="also the simulated 0.5 |m| magnet (rounds, (F2))")
    p.add_argument("--sim-seeds", default="7", help="seeds of the simulations of --sim (default 7, the test's)")
    args = p.parse_args(argv)
    if args.sim:
        for seed in [int(x) for x in args.sim_seeds.split(",") if x.strip()]:
            simulated(seed)
    for path in (select_trials(args.trials) if args.trials else []):
        hits = [path]
        s = load_session(path)
        print(f"{hits[0].stem}:", flush=True)
        for name in [x.strip() for x in args.effects.split(",") if x.strip()]:
            study(s, name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
