"""Benchmark (issue 5, S20-M): where a stationary magnet really disturbs the field in BROAD 28/30, beside
what the blind diagnosis finds (verdict, windows, shrink, ranking) and the IoU between the two.

Truth-side reference (scoring only, never given to the estimator): the magnetometer predicted from the
OPTICAL orientation opt_quat alone,

    y_j ≈ K vec(nRb,j) + o      (K 3×9, o 3: Kok & Schön's D bRn n_mag + o for any D, n_mag, and a constant
                                 optical-to-IMU misalignment absorbed in K)                               (R0)

fitted by least squares on every sample with a finite opt_quat, trimmed 5 times to the samples within 3
robust σ of the fit (the disturbed samples fall out); the deviation e_j = |y_j − ŷ_j| / |m| (|m| the median
|ŷ − o|), median-filtered over 0.25 s. Rule: a sample is disturbed when e ≥ 0.10 — the relevance threshold
(M2) of magnetic_disturbance (10 % of |m|); "sustained" intervals are the disturbed runs (gaps < 0.5 s
merged) lasting ≥ 1 s (a window-based model can fit a field over a window, not a 0.2 s spike).
The reference's own floor on undisturbed trials: `--truth-only --trials 04,15` (slow rotation; fast
translation, where optical/IMU timing and lever arm make the largest misfit).

IoU = |diagnosed ∩ reference| / |diagnosed ∪ reference| in seconds, the diagnosed set being the union of
magnetic_disturbance's fitted windows (whether or not it is the verdict).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20_stationary_magnet.py --trials 28,30 --compare
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20_stationary_magnet.py --trials 21,24,26 --compare   (controls)
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20_stationary_magnet.py --trials 28 --magnet-visit-drift --compare
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20_stationary_magnet.py --truth-only --trials 28,30,04,15,01
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/m20_stationary_magnet.py --truth-only --explain --trials 28,30
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.common import select_trials  # noqa: E402

THRESHOLD = 0.10             # fraction of |m|: magnetic_disturbance's relevance (M2)
SMOOTH_S = 0.25
MERGE_S = 0.5
SUSTAINED_S = 1.0


def reference(session) -> dict:
    """(R0): the per-sample deviation e (fraction of |m|), the disturbed intervals and the sustained ones."""
    from scipy.ndimage import median_filter

    from imugraph.geometry import quat_to_rotmat

    ok = np.all(np.isfinite(session.quat), axis=1) & np.all(np.isfinite(session.mag), axis=1)
    X = np.zeros((session.n, 10))
    X[ok, :9] = quat_to_rotmat(session.quat[ok]).reshape(-1, 9)
    X[:, 9] = 1.0
    keep = ok.copy()
    for _ in range(5):                                               # trimmed least squares of (R0)
        K, *_ = np.linalg.lstsq(X[keep], session.mag[keep], rcond=None)
        err = np.linalg.norm(np.nan_to_num(session.mag) - X @ K, axis=1)
        keep = ok & (err < 3.0 * 1.4826 * np.median(err[keep]))
    y_hat = X @ K
    field = float(np.median(np.linalg.norm(y_hat[ok] - K[9], axis=1)))
    e = np.where(ok, err / field, 0.0)
    e = median_filter(e, size=int(round(SMOOTH_S * session.rate)) | 1)
    iv = intervals(session.t, e >= THRESHOLD)
    return {"e": e, "field": field, "intervals": iv,
            "sustained": [w for w in iv if w[1] - w[0] >= SUSTAINED_S]}


def intervals(t: np.ndarray, flag: np.ndarray) -> list:
    """Runs of `flag` as (t_start, t_end), runs closer than MERGE_S merged."""
    d = np.diff(np.r_[0, flag.astype(int), 0])
    out = []
    for i, j in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1):
        if out and t[i] - out[-1][1] <= MERGE_S:
            out[-1] = (out[-1][0], float(t[j]))
        else:
            out.append((float(t[i]), float(t[j])))
    return out


def by_distance(path: Path, session, ref: dict) -> str:
    """Position dependence (truth side, opt_pos of the .mat): median e during movement by the optical
    distance to where e is largest during movement (≈ the magnet), bins 0–5–10–20–40–∞ cm."""
    from scipy.io import loadmat

    try:
        pos = np.asarray(loadmat(str(path), variable_names=["opt_pos"])["opt_pos"], float)
    except (KeyError, OSError, ValueError):
        return "no opt_pos"
    mv = session.movement.astype(bool) if session.movement is not None else np.ones(session.n, bool)
    ok = mv & np.all(np.isfinite(pos), axis=1)
    if not ok.any():
        return "no opt_pos in movement"
    p0 = pos[np.flatnonzero(ok)[np.argmax(ref["e"][ok])]]
    d = np.linalg.norm(pos - p0, axis=1)
    out = []
    for lo, hi in [(0, .05), (.05, .1), (.1, .2), (.2, .4), (.4, np.inf)]:
        m = ok & (d >= lo) & (d < hi)
        out.append(f"{100 * lo:.0f}–{'∞' if hi == np.inf else f'{100 * hi:.0f}'} cm: "
                   + (f"{np.median(ref['e'][m]):.2f} ({m.sum() / session.rate:.1f} s)" if m.any() else "—"))
    return "median e by distance to the largest deviation in movement: " + ", ".join(out)


def heading_error(fit, session) -> np.ndarray:
    """(N,) heading of the base fit's nRb against the optical one, degrees (scoring only): the constant
    rotation A between the two navigation frames from the SVD of Σ nRb,fit nRb,optᵀ, then the vertical
    component of log(nRb,fit (A nRb,opt)ᵀ) (nav z is up in both). NaN where opt_quat is missing."""
    from imugraph.geometry import logmap, quat_to_rotmat

    ok = np.all(np.isfinite(session.quat), axis=1)
    R_opt = np.full((session.n, 3, 3), np.nan)
    R_opt[ok] = quat_to_rotmat(session.quat[ok])
    M = np.einsum("nij,nkj->ik", fit.nRb[ok], R_opt[ok])
    U, _, Vt = np.linalg.svd(M)
    A = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out = np.full(session.n, np.nan)
    E = np.einsum("nij,nkj->nik", fit.nRb[ok], A @ R_opt[ok])
    out[ok] = np.degrees([logmap(x)[2] for x in E])
    return out


def iou(t: np.ndarray, a: list, b: list) -> float:
    """Intersection over union, in samples (≈ seconds), of two sets of (t_start, t_end) intervals."""
    from imugraph.diagnose.effects.base import window_mask

    ma, mb = window_mask(t, a), window_mask(t, b)
    u = int((ma | mb).sum())
    return float((ma & mb).sum()) / u if u else float("nan")


def fmt(iv: list, n: int = 12) -> str:
    s = " ".join(f"{a:.1f}–{b:.1f}" for a, b in iv[:n])
    return s + (f" (+{len(iv) - n} more)" if len(iv) > n else "")


def diagnosed(session, opt, label: str, ref: dict) -> None:
    """One diagnosis: prints verdict, magnetic_disturbance's windows, shrink, ranking, IoU against `ref`."""
    from imugraph.diagnose.run import diagnose

    c0 = time.process_time()
    d = diagnose(session, opt)
    cpu = time.process_time() - c0
    mag = next((r for r in d.effects if r.name == "magnetic_disturbance"), None)
    wins = [(w["t_start"], w["t_end"]) for w in ((mag.params or {}).get("windows", []) if mag else [])]
    t = session.t
    rank = ", ".join(f"{r.name} {r.penalised:+.2f}{' sig' if r.significant else ''}{' rel' if r.relevant else ''}"
                     for r in d.effects[:3])
    md = (f"shrink {mag.shrink:.2f} pen {mag.penalised:+.2f} size {(mag.size or {}).get('value', 0.0):.3f} "
          f"{'sig' if mag.significant else 'not-sig'} {'rel' if mag.relevant else 'not-rel'} stage {mag.stage}"
          if mag else "not tried")
    print(f"  [{label}] verdict {d.verdict} | magnetic_disturbance windows {fmt(wins) or '—'} | {md}\n"
          f"      IoU vs all {iou(t, wins, ref['intervals']):.2f}, vs sustained {iou(t, wins, ref['sustained']):.2f}"
          f" | ranked: {rank} | CPU {cpu:.0f} s", flush=True)
    locs = [x for x in d.locations if x["channel"] == "mag"]
    print("      gap localisation, mag: " + (", ".join(f"{x['t_start']:.0f}–{x['t_end']:.0f} s ({x['score']:.2f})"
                                                   for x in locs[:8]) or "—"), flush=True)
    if mag is not None and mag.loglik_per_channel:
        ll = mag.loglik_per_channel
        print("      magnetic_disturbance held-out log score gain on its support (A4), nats/sample: "
              + ", ".join(f"{c} {ll[c]:+.2f}" for c in ll) + f"; folds "
              + " ".join(f"{g:+.1f}" for g in (mag.loglik_folds or [])), flush=True)


def explain(session, ref: dict) -> None:
    """Why the windows are what they are (base fit only, no diagnosis): (M3')'s accepted windows before the
    edge refinement, find_windows by default and with (M6), and per (M6) window the whitened RMS of the
    magnetometer residual before (base fit) and after the (M1) fit on all samples, in the window's interior
    (edges ± 0.5 s out) and on its edges (± 0.5 s); the base residual |r|/|m| on the reference's sustained
    intervals."""
    from imugraph.diagnose.effects import magnetic_disturbance as md
    from imugraph.diagnose.fit import base_options, fit_base

    fit = fit_base(session, base_options(5.0))
    t, r, sig = session.t, fit.residuals["mag"], np.asarray(fit.sigma["mag"], float)
    earth = md.earth_field_norm(fit)
    last = len(t) - 1
    raw = md.step_windows_refit(fit, r, earth, max_windows=8)[0]
    print(f"  base fit: |m| {earth:.1f}, σ_mag {np.round(sig, 2).tolist()}; (M3') accepted (up to 8, before "
          f"refinement): {fmt([(t[a], t[min(b, len(t)) - 1]) for a, b in raw]) or '—'}")
    saved = md.INTERMITTENT
    try:
        md.INTERMITTENT = False
        w_def = md.EFFECT.find_windows(fit)
        md.INTERMITTENT = True
        w_int = md.EFFECT.find_windows(fit)
        corr = md.EFFECT.fit(fit, np.ones(fit.n, bool))
    finally:
        md.INTERMITTENT = saved
    print(f"  find_windows: default {fmt(w_def) or '—'} | (M6) {fmt(w_int) or '—'} | (M6)+(R1) fitted "
          f"{fmt([(w['t_start'], w['t_end']) for w in corr.params['windows']]) or '—'}")
    after = corr.raw_residuals(fit)["mag"]
    rms = lambda x, m: float(np.sqrt(np.nanmean((x[m] / sig) ** 2))) if m.any() else float("nan")  # noqa: E731
    for w in corr.params["windows"]:
        a, b = w["t_start"], w["t_end"]
        inner = (t >= a + 0.5) & (t <= b - 0.5)
        edge = ((t >= a - 0.5) & (t <= a + 0.5)) | ((t >= b - 0.5) & (t <= b + 0.5))
        print(f"    window {a:.1f}–{b:.1f}: whitened RMS interior {rms(r, inner):.1f} → {rms(after, inner):.1f}, "
              f"edges {rms(r, edge):.1f} → {rms(after, edge):.1f}")
    if corr.params["windows"]:                 # the effect's refit θ* ((F1), FieldRemoved), default and (M6)
        from imugraph.diagnose.effects.base import window_mask

        sup = window_mask(t, [(w["t_start"] - 1.0, w["t_end"] + 1.0) for w in corr.params["windows"]])
        sg = np.asarray(fit.sigma["gyr"], float)
        g = lambda f, m: float(np.sqrt(np.nanmean((f.residuals["gyr"][m] / sg) ** 2)))  # noqa: E731
        for label, flag in (("default", False), ("(M6)", True)):
            try:
                md.INTERMITTENT = flag
                ext, _ = md.EFFECT.refit(fit, 2)
            finally:
                md.INTERMITTENT = saved
            print(f"    refit θ* {label}: gyro whitened RMS (base σ) base → θ*: all {g(fit, np.ones(len(t), bool)):.1f}"
                  f" → {g(ext, np.ones(len(t), bool)):.1f}, (M6) support (windows ± 1 s) {g(fit, sup):.1f} → "
                  f"{g(ext, sup):.1f}, outside {g(fit, ~sup):.1f} → {g(ext, ~sup):.1f}")
    e = np.linalg.norm(r, axis=1) / earth
    from imugraph.diagnose.effects.base import detect_windows

    z2 = np.sum((r / sig) ** 2, axis=1) / 3.0              # find_windows' excess-energy detector, any length
    cand = sorted(detect_windows(t, z2, smooth_s=1.0, factor=4.0, min_s=0.0, merge_s=2.0))
    print("    excess-energy runs of the base residual (4× quiet, merged < 2 s, any length): "
          + (", ".join(f"{t[a]:.1f}–{t[b - 1]:.1f} (|r|/|m| max {np.nanmax(e[a:b]):.2f})" for a, b in cand[:10]) or "—"))
    yaw = heading_error(fit, session)
    for a, b in ref["sustained"]:
        m = (t >= a) & (t <= b)
        near = ((t >= a - 5.0) & (t < a)) | ((t > b) & (t <= b + 5.0))
        print(f"    reference {a:.1f}–{b:.1f}: base residual |r|/|m| median {np.nanmedian(e[m]):.2f}, max "
              f"{np.nanmax(e[m]):.2f} (reference e median {np.median(ref['e'][m]):.2f}); base fit's heading error "
              f"against the optical one: median {np.nanmedian(yaw[m]):+.1f}° in it, {np.nanmedian(yaw[near]):+.1f}° "
              f"over the 5 s on either side (max |change| {np.nanmax(np.abs(yaw[m] - np.nanmedian(yaw[near]))):.1f}°)")
    mv = session.movement.astype(bool) if session.movement is not None else np.ones(len(t), bool)
    print(f"    in movement: base residual |r|/|m| median {np.nanmedian(e[mv]):.3f}, 99th pct "
          f"{np.nanpercentile(e[mv], 99):.3f}; reference e median {np.median(ref['e'][mv]):.3f} (at rest "
          f"{np.median(ref['e'][~mv]) if (~mv).any() else float('nan'):.3f})", flush=True)


def main(argv=None) -> int:
    from imugraph.diagnose.bench import diagnose_options, model_arguments
    from imugraph.io.readers import load_session

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", default="28,30", help="BROAD trial numbers, comma separated (default 28,30)")
    p.add_argument("--truth-only", action="store_true", help="only the reference (R0), no diagnosis")
    p.add_argument("--explain", action="store_true",
                   help="also the base fit's windows and the (M1) residual per window (no diagnosis with --truth-only)")
    p.add_argument("--compare", action="store_true",
                   help="diagnose twice per trial: the options given, then the same with --magnet-intermittent")
    model_arguments(p)
    args = p.parse_args(argv)
    opt = diagnose_options(args)
    for path in (select_trials(args.trials) if args.trials else []):
        hits = [path]
        s = load_session(path)
        ref = reference(s)
        tot = sum(b - a for a, b in ref["intervals"])
        sus = sum(b - a for a, b in ref["sustained"])
        print(f"{hits[0].stem}: |m| {ref['field']:.1f}, reference (R0) e ≥ {THRESHOLD:.2f} |m|: "
              f"{len(ref['intervals'])} intervals, {tot:.1f} s; sustained (≥ {SUSTAINED_S:.0f} s): "
              f"{fmt(ref['sustained']) or '—'} ({sus:.1f} s); max e {ref['e'].max():.2f}", flush=True)
        print(f"  all intervals: {fmt(ref['intervals'], 40) or '—'}", flush=True)
        print(f"  {by_distance(hits[0], s, ref)}", flush=True)
        if args.explain:
            explain(s, ref)
        if args.truth_only:
            continue
        diagnosed(s, opt, "options as given", ref)
        if args.compare:
            diagnosed(s, replace(opt, magnet_intermittent=True), "+ magnet_intermittent", ref)
    return 0


if __name__ == "__main__":
    sys.exit(main())
