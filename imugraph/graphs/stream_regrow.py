"""The bootstrap that keeps growing while the stream runs (`stream_session(..., bootstrap_regrow=...)`, helper S22):
`push_regrow`, split from stream_run."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from imugraph.geometry import quat_conj, quat_mul
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_run import BIAS_TOL, _refusal, rest_gyro_bias, session_smoother, weak_centre
from imugraph.io.session import Session


def push_regrow(session: Session, smoother: StreamSmoother, n_boot: int, bootstrap_s: float, options: StreamOptions,
                mode: bool | str, say: Callable[[str], None] = lambda m: None, grow: float = 1.5, centre: bool = False,
                align: bool = False, latency_s: float | None = None, confirm: float | None = None,
                confirm_k: float = 3.0, confirm_deg: float = 0.5):
    """Stream `session` (as stream_session's loop) while the bootstrap window keeps growing (helper S22): the start
    calibration is a capped bootstrap's weak fallback (calibrate's regularised estimate; BROAD capped at 30 s: 7.7°
    filtered, and θ's pin keeps the orientations at that start, stream_calstate eq. 3). At each growth span
    T_j = bootstrap_s·grow^j beyond the start's, once the stream has seen the rows of [0, T_j] (n_j rows), a batch
    `calibrate` on those rows only (causal), as bootstrap_calibration's next window would; if it identifies D, o (or,
    mode "weak", its weak fallback of the longer window) and its gyro bias agrees with the initial rest's (BIAS_TOL),
    a new smoother started with it replays rows [0, n_j) (outputs discarded) and takes over the live stream once the
    CPU time of that work has passed in stream time (rows meanwhile still from the old smoother, then caught up):

        switch row = first i with t_i ≥ t_{n_j − 1} + CPU(calibrate + replay)                                   (R1)

    latency_s: a fixed stand-in for CPU(calibrate + replay) in (R1), so that runs repeat exactly (None: the measured
    CPU time, as a live stream would see it — results then vary slightly from run to run, e.g. BROAD 06 filtered
    1.0315 / 1.0318 / 1.0340° in three runs).

    Growth stops after an identified window (confirm None) or when the next window reaches the session's end.
    confirm (helper S23, a factor c ≥ 1): an identified window is not trusted at once. Growth goes on; a longer
    identified window j is compared with the current calibration c (found on span T_c): it differs when both
    (C1) z > confirm_k (D, o, dip beyond their reported std, `regrow_consistent`) and (C2) the calibrated field
    directions of the window's samples differ by more than confirm_deg RMS (`field_direction_change`: what the
    orientation sees; a change of D's scale alone, BROAD 06's windows drift 2.5 % at z ≈ 4–9 but 0.2–0.8°, does
    not turn it). A differing window replaces the current one (a switch: the earlier window saw a different
    majority state, e.g. BROAD 32's magnet for 58 of its first 101 s: z 643, 63°); an agreeing one with
    T_j ≥ c·T_c confirms it: its calibration (more data, the same state) is switched to and growth stops. Weak windows after an identified
    one are not tried (calibrate without its weak fallback). centre: a weak
    window's calibration replaced by `weak_centre`. align: from a switch at row i on, the new smoother's filtered
    q_i is output as q_ψ ⊗ q_i, q_ψ the heading part (about nav z) of the last output before it times the new
    smoother's own estimate of that row inverted (no heading jump; the frame is then the start's):

        Δ = q_out(i−1) ⊗ q_new(i−1)⁻¹,   ψ = 2·atan2(Δ_z, Δ_w),   q_ψ = (cos ψ/2, 0, 0, sin ψ/2)                  (R2)
    Returns (filtered (N, 4), the live smoother at the end, log: one dict per window tried, live: the per-update
    times the user waited for — each smoother's updates while it was the live one, without the replays and
    catch-ups done in the background (`live_stats`))."""
    from imugraph.calibration.ml import Options, calibrate     # at call time, as before (tests stub ml.calibrate)
    from imugraph.errors import CalibrationError

    t, t0 = session.t, float(session.t[0])
    rows = np.column_stack((t, session.gyr, session.acc, session.mag)).tolist()
    span = bootstrap_s
    while int(np.searchsorted(t, t0 + span, side="right")) <= n_boot:     # the first window longer than the start's
        span *= grow
    n_next = int(np.searchsorted(t, t0 + span, side="right"))
    b_rest = rest_gyro_bias(session)
    out, log, pending = [], [], None       # pending: (smoother, rows it has, stream time it is ready at, its last output)
    yaws, cur = [], np.array([1.0, 0.0, 0.0, 0.0])     # align: (first row, q_ψ) per switch (R2)
    push = smoother.push_floats
    cur_cal, cur_span, cur_ident = smoother.cal, float(t[n_boot - 1] - t0) if n_boot else 0.0, False
    live, live_from = [], (0, 0)     # (smoother, first stats entry of its live updates) per smoother that was live
    for i, row in enumerate(rows):
        if pending is not None and row[0] >= pending[2]:          # (R1): catch up, switch
            new, have = pending[:2]
            for r in rows[have:i]:
                q_last = new.push_floats(*r)
            if align:
                q_last = q_last if i > have else pending[3]
                d = quat_mul(quat_mul(cur, np.asarray(out[-1], float)), quat_conj(np.asarray(q_last, float)))
                psi = 2.0 * np.arctan2(d[3], d[0])
                cur = np.array([np.cos(psi / 2), 0.0, 0.0, np.sin(psi / 2)])
                yaws.append((i, cur))
            live.append((smoother, live_from))
            smoother, push, pending = new, new.push_floats, None
            live_from = (len(new.stats.update_s), len(new.stats.between_s))     # its replay + catch-up: background
            pend_entry["switched_t"] = float(row[0] - t0)
        if i == n_next and n_next < session.n:
            cpu0 = time.process_time()
            entry = {"span_s": float(t[i - 1] - t0), "rows": i, "identified": None, "switched_t": None}
            try:
                weak_ok = mode == "weak" and not cur_ident          # no weak window after an identified one
                est = calibrate(session.slice(0, i), Options(keyframe_hz=options.keyframe_hz), allow_weak=weak_ok)
                new_cal = est.calibration
                entry["identified"] = bool(new_cal.coverage.get("identifiable", True)) if isinstance(new_cal.coverage, dict) else True
                off = None if b_rest is None else float(np.max(np.abs(new_cal.gyro_bias - b_rest)))
                if off is not None and off > BIAS_TOL:
                    entry["refused"], new_cal = f"gyro bias {off:.3f} rad/s off the initial rest's", None
            except CalibrationError as e:
                entry["refused"], new_cal = _refusal(str(e)), None
            done = False
            if new_cal is not None and cur_ident and confirm is not None:       # (C1): the consistency test
                entry["z_max"] = z = regrow_consistent(cur_cal, new_cal)
                entry["dir_deg"] = a = field_direction_change(cur_cal, new_cal, session.mag[:i])
                same = z <= confirm_k or a <= confirm_deg                   # not both (C1) and (C2)
                if same and entry["span_s"] < confirm * cur_span:
                    entry["decision"], new_cal = "consistent, not yet confirmed", None
                elif same:
                    entry["decision"], done = f"confirmed (T ≥ {confirm:g}·{cur_span:.1f} s)", True
                else:
                    entry["decision"] = f"differs from the current calibration ({z:.1f} std, {a:.2f}°)"
            if new_cal is not None:
                new_cal = weak_centre(new_cal, session, i) if centre else new_cal
                entry.update(D=new_cal.D.tolist(), o=new_cal.o.tolist())
                new = session_smoother(session, new_cal, i, options)
                for r in rows[:i]:
                    q_rep = new.push_floats(*r)
                wait = time.process_time() - cpu0 if latency_s is None else float(latency_s)
                pending, pend_entry = (new, i, float(t[i - 1]) + wait, q_rep), entry
                cur_cal, cur_span, cur_ident = new_cal, entry["span_s"], bool(entry["identified"])
            entry["cpu_s"] = time.process_time() - cpu0
            entry["kind"] = "refused" if "refused" in entry else "identified" if entry["identified"] else "weak"
            log.append(entry)
            kind = "refused (" + entry["refused"] + ")" if "refused" in entry else entry["kind"]
            say(f"bootstrap regrow on the first {entry['span_s']:.1f} s: {kind}"
                + (f"; {entry['decision']}" if "decision" in entry else "") + ("; switching" if new_cal is not None else ""))
            if done or (confirm is None and entry["identified"] and new_cal is not None):
                n_next = session.n                                 # done growing
            else:
                span *= grow
                n_next = int(np.searchsorted(t, t0 + span, side="right"))
        out.append(push(*row))
    filtered = np.array(out, float).reshape(-1, 4)
    live.append((smoother, live_from))
    if align:
        for j, (i0, q) in enumerate(yaws):      # each row's q_ψ was known when it was output (causal)
            i1 = yaws[j + 1][0] if j + 1 < len(yaws) else len(filtered)
            filtered[i0:i1] = quat_mul(q, filtered[i0:i1])
    return filtered, smoother, log, live_stats(live)


def live_stats(live: list) -> dict:
    """The update / between-keyframe times of the live smoothers only (helper S23): for each (smoother, start) the
    entries from start on (start: 0 for the first smoother, else (updates, between steps) after its replay and
    catch-up), concatenated: what timing.json's p50 / p99 / max must count. The replays are background work (R1)."""
    out = {k: [] for k in ("update_s", "update_cpu_s", "between_s", "between_cpu_s", "update_t")}
    for sm, start in live:
        u0, b0 = start
        st = sm.stats
        if hasattr(sm, "times"):            # update j adds keyframe j + 1 (StreamSmoother._close): its time
            out["update_t"] += list(np.asarray(sm.times(), float)[1:][u0:len(st.update_s)])
        out["update_s"] += list(st.update_s[u0:])
        out["update_cpu_s"] += list(st.update_cpu_s[u0:])
        out["between_s"] += list(st.between_s[b0:])
        out["between_cpu_s"] += list(st.between_cpu_s[b0:])
    return out


def field_direction_change(cal_c, cal_j, y_mag: np.ndarray, stride: int = 10) -> float:
    """RMS angle (degrees) between the calibrated field directions of the raw samples y_mag (every stride-th finite
    row) under two calibrations (helper S23): the part of a calibration change the orientation sees:

        m_k = D⁻¹(y_k − o) / |D⁻¹(y_k − o)|,   δ = sqrt(mean_k ∠(m_c,k, m_j,k)²)                                  (C2)

    A common scale of D (the field's magnitude) leaves every m_k, and so the orientation, unchanged."""
    y = np.asarray(y_mag, float)[::stride]
    y = y[np.all(np.isfinite(y), axis=1)]
    if not len(y):
        return 0.0
    m = [np.linalg.solve(c.D, (y - c.o).T).T for c in (cal_c, cal_j)]
    m = [v / np.linalg.norm(v, axis=1, keepdims=True) for v in m]
    cos = np.clip(np.sum(m[0] * m[1], axis=1), -1.0, 1.0)
    return float(np.degrees(np.sqrt(np.mean(np.arccos(cos) ** 2))))


def regrow_consistent(cal_c, cal_j) -> float:
    """Largest standardised difference between two identified calibrations (helper S23), over D (9), o (3), dip:

        z = max_i |θ_j,i − θ_c,i| / sqrt(σ_j,i² + σ_c,i²)                                                      (C1)

    σ: each calibration's reported marginal std (`Calibration.std`). The windows are nested ([0, T_c] ⊂ [0, T_j]),
    so under "one state throughout" the two estimates are positively correlated and Var(θ_c − θ_j) ≈ σ_c² − σ_j²
    (Hausman): the sum in (C1) over-states it, i.e. the test is conservative — it switches only on a clear
    difference (BROAD 32: o_z 58.4 vs 0.2 µT, σ ≈ 0.07; BROAD 06's consecutive windows: z ≤ 2). A missing std: inf."""
    z = []
    for key in ("D", "o", "dip_deg"):
        a = np.atleast_1d(np.asarray(getattr(cal_c, key), float)).ravel()
        b = np.atleast_1d(np.asarray(getattr(cal_j, key), float)).ravel()
        sc, sj = cal_c.std.get(key), cal_j.std.get(key)
        if sc is None or sj is None:
            return float("inf")
        sig = np.sqrt(np.atleast_1d(np.asarray(sc, float)).ravel() ** 2 + np.atleast_1d(np.asarray(sj, float)).ravel() ** 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.abs(b - a) / sig
        r = r[np.isfinite(r) | (np.abs(b - a) > 0)]          # 0/0 (a fixed component): no evidence either way
        z.append(np.nan_to_num(r, nan=np.inf))
    z = np.concatenate(z)
    return float(z.max()) if z.size else 0.0
