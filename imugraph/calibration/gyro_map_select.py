"""The gyro scale/misalignment E kept or dropped per recording by a held-out ACCELEROMETER test
(Options.gyro_map_select; issue 2c, helper H4).

E (calibration/gyro_map.py) is estimated behind a coverage and a settling gate, but passing them does not say
that Ê predicts better than E = 0: on BROAD 02 the gated Ê (x, y scale +0.25 %, −0.32 %) disagrees with the one
of 01/04 (same gyro) and costs 0.05° against the optical truth. The held-out MAGNETOMETER score
(calibration/field_select.py) cannot judge E: the field perturbation d_k absorbs what the gyro gets wrong between
magnetometer samples (BROAD 01/02/04: map on vs off within 0.6 %). The accelerometer can, without any smoother:
where it sees gravity alone at both ends of a stretch, the gyro must carry one gravity direction onto the other.

Test (K-fold over time blocks, like field_select):

    fold f: blocks b (block_s seconds) with b mod F = f are held out — their keyframe intervals never inform E
    (session.meta["gyro_map_exclude"], read by gyro_map.coverage_gate); E is estimated as configured from the
    rest (Ê_f, with the fold run's gyro bias b̂_f). The reference is E = 0 with the plain model's bias b̂_0.
    In each held-out block b, with W0, W1 its first and last window_s seconds (every sample clean:
    | |b_acc| − g | < acc_tol) and the strapdown rotation from the block's first sample j0,

        ω_i = (I + E) b_gyr,i − b̂(i),     R_i = Π_{j0 ≤ l < i} Exp(ω_l Δt_l)       (body i → body j0)
        ĝ_0 = Σ_{i∈W0} R_i b_acc,i,       ĝ_1 = Σ_{i∈W1} R_i b_acc,i               (gravity, body frame j0)
        s_b = |ĝ_1/|ĝ_1| − ĝ_0/|ĝ_0||²     (≈ the squared angle the gyro got wrong across the block, rad²;
                                            blind only to rotation about gravity, which the magnetometer judges)

    and z = mean_b(s_b(E = 0) − s_b(Ê)) / SE over the held-out blocks (paired: the linear acceleration at the
    window ends is common to both). E is kept when z ≥ z_min (Ê carries gravity across the blocks it never saw
    significantly better), else the recording is calibrated with E = 0.

No smoother state enters s_b (only Ê and the bias: the whole recording's, of the model with E for Ê_f and of the
plain model for E = 0). In the fold runs the held-out intervals' gyro factors carry no weight in the E rounds
(gyro_map.GyroMapState, exclude), the coverage gate is dropped and the settling gate relaxed to "steps shrink"
(contraction < 1): both gates are the whole recording's, already passed. The optical truth is not used.
Cost: where the whole recording's E passes its gates, F + 1 more calibrations and F + 1 strapdown
integrations (BROAD 01: 4.5 calibrations' time); elsewhere none (E = 0 already).

Measured (H4; Options.gyro_map_select stays OFF):
  * simulation (tests/test_calibration_gyro_map_select.py, 90 s at 50 Hz): a true E of diag(2, −1.5, 1) % is kept
    (z 4.2, Ê within 0.1 % of it); without one, the Ê the gates let through is dropped (z −2.5);
  * BROAD (benchmarks/h4_gyro_map_select.py 01,02,04): z −2.42 / −2.26 / −1.88 — all three dropped, so 02
    gains (0.473 → 0.423°) but 01 and 04 lose what the map gives them (README 0.77 → 1.232°, 0.56 → 1.173°);
  * why it cannot separate them: its power at these E is too low and E's gain on 01/04 is heading, which the
    accelerometer does not see. On 01 with the plain model's bias and all 4 s blocks (in-sample, favouring E):
    E = +0.5 %·I changes the gravity carry by z −0.10, −0.5 %·I by z −1.92, +1 %·I by z −1.38, the whole
    recording's own Ê by z −1.57 (z −0.98 with its own bias; 02: −0.89). A quadratic through the three scalar
    points puts the accelerometer's best common scale at +0.23 % (Ê's diagonal: mean +0.22 %), worth only
    0.773 → 0.752° of carry RMS: agreement, but far below significance at 35 blocks;
  * other hold-outs tried: withholding the ACCELEROMETER of the blocks (its velocity increments without
    information) broke the calibration itself (01: 1.23 → 5.3°, held and kept blocks alike: the bounded-velocity
    chain loses its long-horizon hold on tilt); contiguous halves (Ê from one half, carry on the other) gave
    z −1.86 / −1.67 / −0.15 (01/02/04): a half's Ê disagrees with the other's (01: E_yy −0.36 % vs +0.23 %),
    the halves turn about different axes and each column of E is excited only by turns about its own axis;
    interleaved blocks whose gyro kept Ê without pulling on it diverged (01: step ratio 1.46), and with their
    gyro raw, Ê took up their rate error as well (≈ 2 × the whole recording's).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from imugraph.calibration.field_select import _paired_z, calibrate_selected, fold_masks
from imugraph.folds import time_blocks
from imugraph.geometry import integrate_gyro, quat_to_rotmat
from imugraph.io.session import Session


def sample_bias(est, session: Session, bias_segment_s: float) -> np.ndarray:
    """(N, 3) gyro bias of each sample from an estimate's segment biases (info["gyro_bias_segments"]; segment
    of a sample by its own time — calibration.ml assigns by the time of the sample's keyframe-interval start,
    so a sample in an interval crossing a segment boundary can differ from ml's)."""
    seg_b = np.atleast_2d(np.asarray(est.info["gyro_bias_segments"], float))
    t = session.t - session.t[0]
    seg = np.floor(t / bias_segment_s).astype(int) if bias_segment_s > 0 else np.zeros(session.n, int)
    if len(seg) and seg[-1] + 1 != len(np.unique(seg)):       # a declared gap longer than a segment: renumbered
        seg = np.unique(seg, return_inverse=True)[1].astype(int)   # as factors.gaps.bias_segments numbers ml's
    return seg_b[np.clip(seg, 0, len(seg_b) - 1)]


def gravity_carry(session: Session, E: np.ndarray, bias_rows: np.ndarray, lead: float, g: float,
                  starts: np.ndarray, stops: np.ndarray, window_s: float, acc_tol: float) -> np.ndarray:
    """(B,) s_b of the stretches [starts_b, stops_b) (sample indices; module docstring); NaN where a stretch is
    shorter than two windows or a window holds a non-clean or non-finite sample."""
    from imugraph.calibration.acc_timing import lead_accelerometer

    a = lead_accelerometer(session.acc, lead, session.gyr, session.dt, session.source) if lead else session.acc
    omega = session.gyr + session.gyr @ np.asarray(E, float).T - bias_rows         # (I + E) b_gyr − b̂
    R = quat_to_rotmat(integrate_gyro(omega, session.dt))                         # body i → body 0
    clean = np.all(np.isfinite(a), axis=1) & (np.abs(np.linalg.norm(a, axis=1) - g) < acc_tol)
    n_w = max(1, int(round(window_s * session.rate)))
    out = np.full(len(starts), np.nan)
    for b, (i0, i1) in enumerate(zip(starts, stops)):
        if i1 - i0 < 2 * n_w or not (clean[i0:i0 + n_w].all() and clean[i1 - n_w:i1].all()):
            continue
        R0t = R[i0].T                                                             # body 0 → body j0
        g0 = R0t @ np.einsum("nij,nj->i", R[i0:i0 + n_w], a[i0:i0 + n_w])
        g1 = R0t @ np.einsum("nij,nj->i", R[i1 - n_w:i1], a[i1 - n_w:i1])
        d = g1 / np.linalg.norm(g1) - g0 / np.linalg.norm(g0)
        out[b] = float(d @ d)
    return out


def choose_gyro_map(session: Session, options, full, allow_weak: bool = False):
    """(keep E: bool, report dict, the E = 0 estimate) by the held-out accelerometer test (module docstring).

    full: the estimate of the whole recording with E (its Ê passed the gates; its bias carries the Ê_h)."""
    from imugraph.calibration import ml

    block_s = options.gyro_map_select_block_s
    base = replace(options, field_select=False, gyro_map_select=False, gyro_map_min_turns=0.0,
                   gyro_map_max_contraction=1.0)       # the gates are the whole recording's (passed)
    plain = ml.calibrate(session, replace(base, gyro_map=False), allow_weak=allow_weak)
    tol = options.gyro_map_acc_tol if options.gyro_map_acc_tol is not None else np.inf

    def carry(est, E, starts, stops):
        return gravity_carry(session, E, sample_bias(est, session, options.bias_segment_s),
                             float(est.calibration.acc_lead_samples or 0.0), float(est.info["g"]), starts, stops,
                             options.gyro_map_select_window_s, tol)

    folds = options.gyro_map_select_folds
    masks = fold_masks(session.t, block_s, folds)
    block = time_blocks(session.t, block_s)
    n_b = int(block.max()) + 1
    starts = np.searchsorted(block, np.arange(n_b))
    stops = np.searchsorted(block, np.arange(n_b), side="right")
    s_off = carry(plain, np.zeros((3, 3)), starts, stops)
    s_on, fold_info = np.full(n_b, np.nan), []
    for f, held in enumerate(masks):
        est = ml.calibrate(replace(session, meta=dict(session.meta, gyro_map_exclude=held)), base,
                           allow_weak=allow_weak)                        # Ê_f without the held-out gyro
        E_f = np.asarray(est.calibration.gyro_map, float)
        in_fold = np.arange(n_b) % folds == f
        s_on[in_fold] = carry(full, E_f, starts[in_fold], stops[in_fold])
        fold_info.append({"estimated": bool(est.info.get("gyro_map_gate", {}).get("estimated")), "E": E_f.tolist()})
    z = _paired_z(s_on, s_off)
    both = np.isfinite(s_on) & np.isfinite(s_off)
    report = {"keep": bool(z >= options.gyro_map_select_z), "z": z, "blocks": int(both.sum()),
              "carry_rms_deg": {"map": float(np.rad2deg(np.sqrt(np.mean(s_on[both])))) if both.any() else None,
                                "no_map": float(np.rad2deg(np.sqrt(np.mean(s_off[both])))) if both.any() else None},
              "folds": fold_info}
    return report["keep"], report, plain


def calibrate_chosen(session: Session, options, initial=None, allow_weak: bool = False):
    """ml.calibrate with the per-recording choices that are switched on: the gyro map kept or dropped by
    `choose_gyro_map` (Options.gyro_map_select; tested only where E passes its gates on the full recording) and
    the field process by field_select (Options.field_select). The test's report is in info["gyro_map_select"]."""
    from imugraph.calibration import ml

    opt = replace(options, gyro_map_select=False)
    if opt.field_select:
        def run(o):
            return calibrate_selected(session, o, initial, allow_weak)
    else:
        def run(o):
            return ml.calibrate(session, o, initial=initial, allow_weak=allow_weak)
    if not (options.gyro_map_select and options.gyro_map):
        return run(opt)
    full = run(opt)
    if not full.info.get("gyro_map_gate", {}).get("estimated"):
        full.info["gyro_map_select"] = {"keep": False, "reason": "E not estimated (gates): nothing to test"}
        return full
    keep, report, plain = choose_gyro_map(session, opt, full, allow_weak)
    est = full if keep else (plain if not opt.field_select else run(replace(opt, gyro_map=False)))
    est.info["gyro_map_select"] = report
    return est
