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
                align: bool = False, latency_s: float | None = None):
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

    Growth stops after an identified window or when the next window reaches the session's end. centre: a weak
    window's calibration replaced by `weak_centre`. align: from a switch at row i on, the new smoother's filtered
    q_i is output as q_ψ ⊗ q_i, q_ψ the heading part (about nav z) of the last output before it times the new
    smoother's own estimate of that row inverted (no heading jump; the frame is then the start's):

        Δ = q_out(i−1) ⊗ q_new(i−1)⁻¹,   ψ = 2·atan2(Δ_z, Δ_w),   q_ψ = (cos ψ/2, 0, 0, sin ψ/2)                  (R2)
    Returns (filtered (N, 4), the live smoother at the end, log: one dict per window tried)."""
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
            smoother, push, pending = new, new.push_floats, None
            log[-1]["switched_t"] = float(row[0] - t0)
        if i == n_next and n_next < session.n:
            cpu0 = time.process_time()
            entry = {"span_s": float(t[i - 1] - t0), "rows": i, "identified": None, "switched_t": None}
            try:
                est = calibrate(session.slice(0, i), Options(keyframe_hz=options.keyframe_hz), allow_weak=mode == "weak")
                new_cal = est.calibration
                entry["identified"] = bool(new_cal.coverage.get("identifiable", True)) if isinstance(new_cal.coverage, dict) else True
                off = None if b_rest is None else float(np.max(np.abs(new_cal.gyro_bias - b_rest)))
                if off is not None and off > BIAS_TOL:
                    entry["refused"], new_cal = f"gyro bias {off:.3f} rad/s off the initial rest's", None
            except CalibrationError as e:
                entry["refused"], new_cal = _refusal(str(e)), None
            if new_cal is not None:
                new_cal = weak_centre(new_cal, session, i) if centre else new_cal
                entry.update(D=new_cal.D.tolist(), o=new_cal.o.tolist())
                new = session_smoother(session, new_cal, i, options)
                for r in rows[:i]:
                    q_rep = new.push_floats(*r)
                wait = time.process_time() - cpu0 if latency_s is None else float(latency_s)
                pending = (new, i, float(t[i - 1]) + wait, q_rep)
            entry["cpu_s"] = time.process_time() - cpu0
            log.append(entry)
            say(f"bootstrap regrow on the first {entry['span_s']:.1f} s: "
                f"{'refused (' + entry['refused'] + ')' if new_cal is None else 'identified' if entry['identified'] else 'weak'}")
            if entry["identified"] and new_cal is not None:
                n_next = session.n                                 # done growing
            else:
                span *= grow
                n_next = int(np.searchsorted(t, t0 + span, side="right"))
        out.append(push(*row))
    filtered = np.array(out, float).reshape(-1, 4)
    if align:
        for j, (i0, q) in enumerate(yaws):      # each row's q_ψ was known when it was output (causal)
            i1 = yaws[j + 1][0] if j + 1 < len(yaws) else len(filtered)
            filtered[i0:i1] = quat_mul(q, filtered[i0:i1])
    return filtered, smoother, log
