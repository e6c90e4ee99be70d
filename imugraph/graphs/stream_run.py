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
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.graphs.stream import StreamOptions, StreamSmoother
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


def bootstrap_calibration(session: Session, bootstrap_s: float, keyframe_hz: float = 10.0,
                          allow_weak: bool = True, grow: float = 1.5) -> tuple[Calibration, int]:
    """ML calibration of the first seconds of the stream: (calibration, number of samples used).

    Starts with `bootstrap_s` seconds and, while that window holds too little rotation to identify D and o
    (the coverage check of `calibrate` says so by name), waits for more: the window grows by `grow` until
    it identifies the calibration or the session ends (recordings often start with a long rest: BROAD 01
    rests for its first ≈ 20 s). Then, with allow_weak, the regularised fallback of `calibrate`.

    Raises:
        SessionError: a bootstrap window shorter than 2 s of data.
        CalibrationError: (allow_weak False) no window identifies the calibration.
    """
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.errors import CalibrationError

    span = bootstrap_s
    while True:
        n = int(np.searchsorted(session.t, session.t[0] + span, side="right"))
        if session.t[n - 1] - session.t[0] < 2.0:
            raise SessionError(session.name, "bootstrap_s", f"{bootstrap_s:g} s ({n} samples)",
                               "at least 2 s of data")
        last = n >= session.n
        try:
            est = calibrate(session.slice(0, n), Options(keyframe_hz=keyframe_hz), allow_weak=last and allow_weak)
            return est.calibration, n
        except CalibrationError:
            if last:
                raise
        span *= grow


def timing_summary(update_s: list, seconds: float, n_samples: int, rate: float) -> dict:
    """timing.json: `updates`, `seconds` (streaming wall time), `p50_ms`, `p99_ms` per update, and
    `realtime_factor` (samples per second processed ÷ sampling rate)."""
    ms = np.asarray(update_s, float) * 1e3
    return {"updates": int(ms.size), "seconds": float(seconds),
            "p50_ms": float(np.percentile(ms, 50)) if ms.size else None,
            "p99_ms": float(np.percentile(ms, 99)) if ms.size else None,
            "max_ms": float(ms.max()) if ms.size else None,
            "realtime_factor": float(n_samples / max(seconds, 1e-9) / rate)}


def stream_session(session: Session, cal: Optional[Calibration] = None, options: StreamOptions = StreamOptions(),
                   bootstrap_s: float = 30.0, allow_weak: bool = True,
                   say: Callable[[str], None] = lambda m: None) -> StreamResult:
    """Stream every sample of `session` in time order through a `StreamSmoother`.

    Args:
        session: the recording; cal: calibration to hold fixed (None: bootstrap on the first bootstrap_s s);
        options: `StreamOptions`; allow_weak: see `calibrate`; say: progress callback.

    Returns:
        StreamResult (timing also holds `bootstrap_seconds`, the wall time of the bootstrap calibration).
    """
    n_boot, boot_s = 0, 0.0
    if cal is None:
        say(f"bootstrap calibration on the first {bootstrap_s:g} s")
        start = time.perf_counter()
        cal, n_boot = bootstrap_calibration(session, bootstrap_s, options.keyframe_hz, allow_weak)
        boot_s = time.perf_counter() - start
    n_g = n_boot or session.n
    g0 = float(np.median(np.linalg.norm(session.acc[:n_g], axis=1)))
    smoother = StreamSmoother(cal, session.rate, options, g0=g0)
    filtered = np.empty((session.n, 4))
    say(f"streaming {session.n} samples ({'iSAM2' if options.lag_s is None else f'lag {options.lag_s:g} s'})")
    start = time.perf_counter()
    push = smoother.push
    t, gyr, acc, mag = session.t, session.gyr, session.acc, session.mag
    for i in range(session.n):
        filtered[i] = push(t[i], gyr[i], acc[i], mag[i])
    smoother.finish()
    seconds = time.perf_counter() - start
    smoothed = smoother.smoothed()
    timing = timing_summary(smoother.stats.update_s, seconds, session.n, session.rate)
    timing["bootstrap_seconds"] = boot_s
    return StreamResult(session.t, filtered, smoothed, smoother.cal, timing, smoother.stats.counts(), n_boot,
                        smoother.calibration_history, cal)
