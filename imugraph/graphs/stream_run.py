"""A whole session through `StreamSmoother`, in arrival order: what `imugraph stream` runs.

Calibration: given, or a batch bootstrap — `imugraph.calibration.ml.calibrate` on the first `bootstrap_s`
seconds — as the start (and prior) of the online re-estimation of D, o and the dip
(options.online_calibration; `imugraph.graphs.stream_calib`), or held fixed without it. The stream then
starts at the first sample with that calibration, so the filtered output of the bootstrap seconds is a
replay: causal in the samples, but with a calibration that saw those seconds (`bootstrap_samples` says
how many rows that is).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_online import weak_start
from imugraph.io.session import Session


@dataclass
class StreamResult:
    """Output of `stream_session`.

    Attributes:
        t: (N,) s; filtered: (N, 4) nRb w,x,y,z available when each sample arrived; smoothed: (N, 4) at the end.
        calibration: the calibration at the end (online estimate, or the one held fixed); timing: see
        `timing_summary`; counts: `StreamStats.counts()`.
        bootstrap_samples: rows inside the bootstrap window (0 with a given calibration).
        calibration_history: one row per online refit {t, D, o, dip_deg, std, samples, rejected} ([] without).
        start_calibration: the bootstrap's (or the given) calibration.
        update_t, update_ms, update_cpu_ms: (U,) the stream time of each keyframe update (its new keyframe's
        time, s) and the update's wall and thread-CPU time, ms (for the timing figure; timing holds the summary).
    """

    t: np.ndarray
    filtered: np.ndarray
    smoothed: np.ndarray
    calibration: Calibration
    timing: dict
    counts: dict
    bootstrap_samples: int
    calibration_history: list
    start_calibration: Calibration
    update_t: np.ndarray | None = None
    update_ms: np.ndarray | None = None
    update_cpu_ms: np.ndarray | None = None


def bootstrap_calibration(session: Session, bootstrap_s: float, keyframe_hz: float = 10.0,
                          allow_weak: bool = True, grow: float = 1.5, gyro_map: bool | None = None,
                          overrides: dict | None = None, info: dict | None = None,
                          max_s: float | None = None) -> tuple[Calibration, int]:
    """ML calibration of the first seconds of the stream: (calibration, number of samples used).

    Starts with `bootstrap_s` seconds and, while that window holds too little rotation to identify D and o
    (the coverage check of `calibrate` says so by name), waits for more: the window grows by `grow` until
    it identifies the calibration or the session ends (recordings often start with a long rest: BROAD 01
    rests for its first ≈ 20 s). Then, with allow_weak, the regularised fallback of `calibrate`.

    A window whose gyro bias disagrees with the gyro at the stream's initial rest (if it starts with one,
    `rest_gyro_bias`) by more than `BIAS_TOL` is not accepted either, and the window grows: on BROAD 30
    (a magnet in the room) the 45 s bootstrap returned a gyro bias of 0.27 rad/s (the rest says 0.003) and a
    dip of 86° (69° over the whole trial); streaming with it scored 77° RMS filtered, with the whole-trial
    calibration 1.25° (the calibration itself is imugraph.calibration.ml's; this only refuses its result).

    gyro_map: estimate the gyro scale/misalignment E (`calibration.ml.Options.gyro_map`; None: its default,
    as the batch path); the stream applies (I + E) to every incoming gyro sample (`StreamSmoother.push`).
    overrides: further `calibration.ml.Options` fields (benchmarks: e.g. window_trial_verdict=False); None: defaults.
    info: a dict updated with the accepted calibration's `info` (e.g. its chosen "position_sigma") and, under
    "bootstrap_growth", one (span s, reason) per refused window, "bootstrap_capped" (True: stopped at max_s before the
    session's end); None: not kept.
    max_s: cap of the growth (None: none, until the session ends — on BROAD 10, 12, 15, 16 that is the whole trial,
    so the stream's filtered output there is a replay, not causal; U22 defect 3). At the cap the window is the last
    one tried: with allow_weak the regularised weak fallback of `calibrate`, as at the session's end.

    Raises:
        SessionError: a bootstrap window shorter than 2 s of data.
        CalibrationError: (allow_weak False) no window identifies the calibration.
    """
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.errors import CalibrationError

    if max_s is not None and not (isinstance(max_s, (int, float)) and np.isfinite(max_s) and max_s > 0):
        raise SessionError(session.name, "bootstrap_max_s", repr(max_s), "a positive number of seconds or None")
    span = bootstrap_s
    b_rest = rest_gyro_bias(session)
    growth = []                              # (span, reason) of each refused window
    while True:
        capped = max_s is not None and span >= max_s
        n = int(np.searchsorted(session.t, session.t[0] + (max_s if capped else span), side="right"))
        if session.t[n - 1] - session.t[0] < 2.0:
            raise SessionError(session.name, "bootstrap_max_s" if capped else "bootstrap_s",
                               f"{max_s if capped else bootstrap_s:g} s ({n} samples)", "at least 2 s of data")
        last = n >= session.n or capped
        try:
            opt = Options(keyframe_hz=keyframe_hz) if gyro_map is None else Options(keyframe_hz=keyframe_hz, gyro_map=gyro_map)
            if overrides:
                opt = replace(opt, **overrides)
            est = calibrate(session.slice(0, n), opt, allow_weak=last and allow_weak)
            off = None if b_rest is None else float(np.max(np.abs(est.calibration.gyro_bias - b_rest)))
            if last or off is None or off <= BIAS_TOL:
                if info is not None:
                    info.update(est.info)
                    info.update(bootstrap_growth=growth, bootstrap_capped=bool(capped and n < session.n),
                                bootstrap_max_s=max_s)
                return est.calibration, n
            growth.append((float(session.t[n - 1] - session.t[0]), f"gyro bias {off:.3f} rad/s off the initial rest's"))
        except CalibrationError as e:
            if last:
                raise
            growth.append((float(session.t[n - 1] - session.t[0]), _refusal(str(e))))
        span *= grow


def _refusal(message: str) -> str:
    """A short reason from calibrate's refusal ("too little rotation" from its coverage check), for the progress line."""
    if "too little rotation" in message:
        return "too little rotation"
    found = message.split("found ", 1)[-1]
    return found.split(";")[0][:80]


def bootstrap_note(session: Session, n_boot: int, bootstrap_s: float, info: dict | None = None) -> str:
    """What the bootstrap actually used (U22 defect 3): "the first 186.9 s (grown from 30 s: too little rotation;
    all of the session: its filtered output is a replay, not causal)". info: bootstrap_calibration's (growth reasons)."""
    if n_boot <= 0:
        return "none (calibration given)"
    span = float(session.t[n_boot - 1] - session.t[0])
    growth = (info or {}).get("bootstrap_growth") or []
    parts = []
    if growth:
        reasons = list(dict.fromkeys(r for _, r in growth))
        parts.append(f"grown from {bootstrap_s:g} s: {', '.join(reasons)}")
    if (info or {}).get("bootstrap_capped"):
        parts.append(f"capped at bootstrap_max_s = {info['bootstrap_max_s']:g} s: calibrate's weak fallback if not identified")
    if n_boot >= session.n:
        parts.append("all of the session: its filtered output is a replay, not causal")
    else:
        parts.append(f"{100.0 * n_boot / session.n:.0f} % of the session")
    return f"the first {span:.1f} s ({'; '.join(parts)})"


# rad/s: largest accepted difference between a bootstrap's gyro bias and the gyro's mean at the initial rest
# (BROAD: bias ≈ 0.001–0.01 rad/s, rest noise 0.002 rad/s per sample)
BIAS_TOL = 0.02


def rest_gyro_bias(session: Session, rest_s: float = 2.0, min_fraction: float = 0.9) -> np.ndarray | None:
    """Mean gyro over the rest samples of the first rest_s seconds if the sensor rests there (at least
    min_fraction of them at rest by `imugraph.calibration.rest.detect_rest`, its default thresholds), else None."""
    from imugraph.calibration.rest import detect_rest

    n = int(np.searchsorted(session.t, session.t[0] + rest_s, side="right"))
    if n < 10:
        return None
    part = session.slice(0, n)
    if not (np.all(np.isfinite(part.gyr)) and np.all(np.isfinite(part.acc))):
        return None
    rest = detect_rest(part)
    if rest.mean() < min_fraction:
        return None
    return part.gyr[rest].mean(axis=0)


def select_position(session: Session, options: StreamOptions, bootstrap_s: float = 30.0,
                    allow_weak: bool = True, info: dict | None = None,
                    max_s: float | None = None) -> tuple[Calibration, int, StreamOptions]:
    """StreamOptions.position_select: the bootstrap batch chooses σ_p among the candidates by the Laplace marginal
    likelihood (calibration.position_select eq. J2, "off" = 1e4 a candidate, with position_select_rounds) and the
    stream uses it: (calibration, bootstrap samples, options with position_sigma = the choice, None for "off").
    Why the bootstrap: the stream cannot score a bound it has not yet run; the bootstrap's window is the only
    stretch of the session a whole-posterior comparison can be made on before streaming (it sees only that window:
    a sensor that starts travelling later is not seen travelling). info: updated with the bootstrap's `info`
    (its history holds the candidates' scores under "position_select")."""
    info = {} if info is None else info
    cal, n_boot = bootstrap_calibration(session, bootstrap_s, options.keyframe_hz, allow_weak,
                                        overrides={"position_select": tuple(options.position_select),
                                                   "position_select_rounds": True,
                                                   "position_tau": options.position_tau}, info=info, max_s=max_s)
    return cal, n_boot, replace(options, position_sigma=info.get("position_sigma"))


def session_smoother(session: Session, cal: Calibration, n_boot: int, options: StreamOptions) -> StreamSmoother:
    """A StreamSmoother for `session` started as after a bootstrap over its first n_boot rows (0: none): gravity's
    magnitude g0 from those rows (all rows without one), the weak prior's scale and the detector's learning window
    from them."""
    g0 = float(np.median(np.linalg.norm(session.acc[:n_boot or session.n], axis=1)))
    return StreamSmoother(cal, session.rate, options, g0=g0, weak_scale=weak_scale(session, n_boot),
                          start_window_s=float(session.t[n_boot - 1] - session.t[0]) if n_boot else 0.0)


def weak_scale(session: Session, n: int) -> float | None:
    """s of the batch's weak prior D = s·I over the first n samples (the bootstrap window): the median |y| of its
    field samples, as `calibration.initial.weak_initial` computes it; None without one (n = 0 or no field)."""
    if n <= 0:
        return None
    part = session.slice(0, n)
    y = part.mag[part.mag_valid]
    return float(np.median(np.linalg.norm(y, axis=1))) if len(y) else None


def timing_summary(update_s, seconds: float, n_samples: int, rate: float, update_cpu_s=None,
                   cpu_seconds: float | None = None, between_s=None, between_cpu_s=None) -> dict:
    """timing.json: `updates`, `seconds` (streaming wall time), `p50_ms`, `p99_ms`, `max_ms` per keyframe update,
    and `realtime_factor` (samples per second processed ÷ sampling rate); with CPU times (thread CPU per update,
    process CPU of the whole stream) also `p50_cpu_ms`, `p99_cpu_ms`, `max_cpu_ms`, `cpu_seconds`,
    `cpu_realtime_factor`: the same figures without the time other processes took on a shared machine.
    With the work done between keyframes (StreamSmoother._between_keyframes: the chain lag's marginalisation /
    relinearisation, the online refits; each on a sample of its own): `between_steps`, `p50_between_ms`,
    `p99_between_ms`, `max_between_ms` and the same in CPU time — a push waits for at most one of either."""
    def pct(x, q):
        return float(np.percentile(x, q)) if x.size else None
    ms = np.asarray(update_s, float) * 1e3
    out = {"updates": int(ms.size), "seconds": float(seconds), "p50_ms": pct(ms, 50), "p99_ms": pct(ms, 99),
           "max_ms": float(ms.max()) if ms.size else None,
           "realtime_factor": float(n_samples / max(seconds, 1e-9) / rate)}
    if update_cpu_s is not None:
        cpu = np.asarray(update_cpu_s, float) * 1e3
        out.update(p50_cpu_ms=pct(cpu, 50), p99_cpu_ms=pct(cpu, 99), max_cpu_ms=pct(cpu, 100))
    if cpu_seconds is not None:
        out.update(cpu_seconds=float(cpu_seconds), cpu_realtime_factor=float(n_samples / max(cpu_seconds, 1e-9) / rate))
    for tag, x in (("", between_s), ("_cpu", between_cpu_s)):
        if x is not None:
            b = np.asarray(x, float) * 1e3
            out["between_steps"] = int(b.size)
            out.update({f"p50_between{tag}_ms": pct(b, 50), f"p99_between{tag}_ms": pct(b, 99),
                        f"max_between{tag}_ms": pct(b, 100)})
    return out


def stream_session(session: Session, cal: Optional[Calibration] = None, options: StreamOptions = StreamOptions(),
                   bootstrap_s: float = 30.0, allow_weak: bool = True,
                   say: Callable[[str], None] = lambda m: None, bootstrap: tuple | None = None,
                   bootstrap_max_s: float | None = None, bootstrap_regrow: bool | str = False,
                   bootstrap_weak_centre: bool = False, regrow_align: bool = False, regrow_grow: float = 1.5,
                   regrow_latency_s: float | None = None, regrow_confirm: float | None = None) -> StreamResult:
    """Stream every sample of `session` in time order through a `StreamSmoother`.

    Args:
        session: the recording; cal: calibration to hold fixed (None: bootstrap on the first bootstrap_s s);
        options: `StreamOptions`; allow_weak: see `calibrate`; say: progress callback.
        bootstrap: (calibration, samples) of a bootstrap already computed on this session (`bootstrap_calibration`;
        with cal None): used as if computed here (g0, the detector's learning window, the weak prior's scale).
        bootstrap_max_s: cap of the bootstrap window's growth (`bootstrap_calibration` max_s; None: grows until it
        identifies the calibration or the session ends — the default).
        bootstrap_regrow: with a start calibration that is not identifiable (a capped bootstrap's weak fallback), keep
        growing the bootstrap window while streaming (`push_regrow`, helper S22): True — switch to the first window
        that identifies D, o; "weak" — also to each longer window's weak fallback. False: the start is kept (default).
        bootstrap_weak_centre: a start (or a regrow window) that is not identifiable is streamed with the weak prior's
        centre D = s·I, o = 0 (`weak_centre`) instead of calibrate's regularised estimate. False: as before (default).
        regrow_align: the filtered output after a regrow switch turned about the vertical so that it continues the
        previous smoother's heading (`push_regrow` eq. R2). False: the new smoother's own heading (default).
        regrow_grow: the regrow's window growth factor (bootstrap_calibration's 1.5 by default).
        regrow_latency_s: a fixed switch latency instead of the measured CPU time (`push_regrow` (R1)); repeatable runs.
        regrow_confirm: a factor c (helper S23): after an identified switch keep growing; a longer identified window
        that differs beyond 3 reported std and turns the calibrated field directions by more than 0.5° RMS replaces
        the current calibration, one that agrees and is ≥ c× its span confirms it (`push_regrow`, eqs. C1, C2 in
        stream_regrow). None: stop at the first identified window (default). With the regrow, timing's update / between-keyframe figures count the live smoother's
        updates only (the replays are background work, `stream_regrow.live_stats`); `regrow` lists the windows.

    Returns:
        StreamResult (timing also holds `bootstrap_seconds`, the wall time of the bootstrap calibration,
        `bootstrap_span_s`, the seconds it used, and `bootstrap_note`, the progress line's words on it).
    """
    n_boot, boot_s, boot_info = 0, 0.0, {}
    if cal is None and bootstrap is not None:
        cal, n_boot = bootstrap
    elif cal is None:
        say(f"bootstrap calibration from the first {bootstrap_s:g} s")
        start = time.perf_counter()
        if options.position_select:          # σ_p chosen by the bootstrap (select_position)
            cal, n_boot, options = select_position(session, options, bootstrap_s, allow_weak, info=boot_info,
                                                   max_s=bootstrap_max_s)
            say(f"bootstrap chose position_sigma {options.position_sigma}")
        else:
            cal, n_boot = bootstrap_calibration(session, bootstrap_s, options.keyframe_hz, allow_weak, info=boot_info,
                                                max_s=bootstrap_max_s)
        boot_s = time.perf_counter() - start
        say(f"bootstrap calibration on {bootstrap_note(session, n_boot, bootstrap_s, boot_info)}")
    if bootstrap_weak_centre:
        cal = weak_centre(cal, session, n_boot)
    smoother = session_smoother(session, cal, n_boot, options)
    say(f"streaming {session.n} samples ({'iSAM2' if options.lag_s is None else f'lag {options.lag_s:g} s'})")
    start, start_cpu = time.perf_counter(), time.process_time()
    regrow = None
    if bootstrap_regrow and not weak_start(cal):
        bootstrap_regrow = False                 # an identified (or given) start: nothing to regrow
    if bootstrap_regrow:                         # helper S22: the bootstrap keeps growing while the stream runs
        from imugraph.graphs.stream_regrow import push_regrow
        filtered, smoother, regrow, live = push_regrow(session, smoother, n_boot, bootstrap_s, options, bootstrap_regrow,
                                                       say, grow=regrow_grow, centre=bootstrap_weak_centre,
                                                       align=regrow_align, latency_s=regrow_latency_s,
                                                       confirm=regrow_confirm)
    else:
        push, out = smoother.push_floats, []
        keep = out.append
        # rows as ten Python floats (one tolist per block, not a numpy row view per sample: push_floats, the push
        # path without numpy), the filtered 4-tuples gathered and made one array at the end; blocks keep the
        # lists' memory bounded on long sessions
        for i0 in range(0, session.n, 4096):
            blk = slice(i0, i0 + 4096)
            for row in np.column_stack((session.t[blk], session.gyr[blk], session.acc[blk], session.mag[blk])).tolist():
                keep(push(*row))
        filtered = np.array(out, float).reshape(-1, 4)
    smoother.finish()
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
    smoothed = smoother.smoothed()
    st = smoother.stats
    times = (st.update_s, st.update_cpu_s, st.between_s, st.between_cpu_s) if regrow is None else \
        (live["update_s"], live["update_cpu_s"], live["between_s"], live["between_cpu_s"])   # the live updates only
    timing = timing_summary(times[0], seconds, session.n, session.rate, times[1], cpu_seconds, times[2], times[3])
    timing["bootstrap_seconds"] = boot_s
    timing["bootstrap_span_s"] = float(session.t[n_boot - 1] - session.t[0]) if n_boot else 0.0
    timing["bootstrap_note"] = bootstrap_note(session, n_boot, bootstrap_s, boot_info)
    if regrow is not None:
        timing["regrow"] = regrow
        timing["regrow_cpu_seconds"] = float(sum(e["cpu_s"] for e in regrow))   # calibrate + replays (background)
    update_ms = np.asarray(times[0], float) * 1e3
    update_t = smoother.times()[1:]  # keyframe 0 is the first sample; every update adds k+1 (StreamSmoother._close)
    update_t = update_t if regrow is None else np.asarray(live["update_t"], float)   # the live updates' keyframes
    return StreamResult(session.t, filtered, smoothed, smoother.cal, timing, smoother.stats.counts(), n_boot,
                        smoother.calibration_history, cal, update_t, update_ms,
                        np.asarray(times[1], float) * 1e3)


def weak_centre(cal: Calibration, session: Session, n: int) -> Calibration:
    """A calibration that is not identifiable (`coverage["identifiable"]` False) moved to its weak prior's centre,
    D = s·I, o = 0 (s = `weak_scale` of the first n rows, as `calibration.initial.weak_initial`); others unchanged.
    Why (helper S22): on a window without rotation (BROAD's first 30 s rest: 0° of rotation) calibrate's regularised
    estimate still moves D, o along the directions the data cannot see (BROAD 06: D ≈ diag(55, 62, 58), o_z = 16.5
    against the 45-s identified window's D ≈ 42·I, o ≈ 0), and the stream's pin holds the orientations there."""
    if not weak_start(cal):
        return cal
    s = weak_scale(session, n) or float(np.cbrt(abs(np.linalg.det(cal.D))))
    return replace(cal, D=s * np.eye(3), o=np.zeros(3))
