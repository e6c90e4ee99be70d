"""Checks a Session before any solver sees it; bad input becomes one clear SessionError.

Every error names the file (`session.source`), the field, what was found and what was expected.
The checks, in order (the first failing one is reported):

1. shapes: t (N,), gyr/acc/mag (N, 3), quat (N, 4), movement (N,), numeric;
2. length: at least `MIN_SAMPLES` samples and `MIN_SECONDS` seconds;
3. time: finite, strictly increasing (unsorted and duplicate stamps are told apart), a plausible time
   base (median step between 1/`MAX_RATE_HZ` and 1/`MIN_RATE_HZ` s, at most `MAX_DURATION_S` in all: stamps in
   ms or µs read as s give a 0.29 Hz "rate" and a runaway solve), no gap longer
   than `GAP_STEPS` median steps unless the reader declared it in ``meta["gaps"]`` (a list of
   ``[t_before, t_after]`` pairs: formats that know about dropouts report them instead of failing);
4. NaN/inf in gyr/acc: runs of at most `MAX_REPAIR_RUN` samples are repaired by linear
   interpolation (recorded in ``meta["repaired"]``), longer runs are an error giving the index range;
5. units: median |acc| in [0.5, 2] looks like g; outside [3, 40] m/s² is implausible.
   Gyroscope in °/s is caught by either of two rules:
   (a) robust maximum (99.9th percentile of |gyr| per axis) above 35 rad/s: no MEMS gyroscope
       range exceeds ±2000 °/s = 34.9 rad/s;
   (b) kinematics, for slow sessions: the gravity direction seen by the accelerometer turns as
       the gyroscope says, b_v(t+T) = Exp(−ω̄T)·b_v(t) (see `gyro_unit_evidence`). The rule fires
       when reading the gyro as °/s predicts the turning with < 50 % of the no-rotation error and
       < 20 % of the error of reading it as rad/s. On real rad/s recordings the °/s reading is
       never better than no rotation (ratio 0.97–1.02: BROAD, Xsens, x-io, Rasteiro), so the rule
       cannot fire on them; where linear acceleration dominates the accelerometer (walking, fast
       translation) it stays silent and rule (a) covers those fast motions.
6. saturation: an axis of gyr or acc that holds its extreme value (|x| = max |x|, same sign) for
   `SAT_RUN` or more consecutive samples;
7. magnetometer: not all NaN, no ±inf, and not constant on any axis over its samples (a dead or
   disconnected magnetometer reads all zeros or one frozen value: no rotation can be seen in it, and the
   solvers fail on it with a singular system);  quat: unit norm where finite.
8. gyroscope (check 'gyr'): not constant on any axis over its finite samples, the dead magnetometer's rule. A
   gyroscope at rest reads its noise, never one value on every sample; all zeros or one frozen value is a dead
   or disconnected sensor, whose "no rotation" the solvers would believe. Run after the saturation check (a
   constant non-zero axis is reported as saturated there) and skipped with it: noise-free simulations hold exact
   constant rates.

Validation never modifies its input: it returns the same Session when nothing was repaired, else
a new one with repaired copies and an updated meta.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable, Optional

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import expmap
from imugraph.io.session import Session

NO_MAG = ("calibrate/smooth/stream need a magnetometer (heading comes from it; 6-axis data give tilt only, which "   # U22 #5
          "imugraph does not output); body sessions without magnetometers: `imugraph mocap` (its default)")
MIN_SAMPLES = 50
MIN_SECONDS = 2.0
GAP_STEPS = 5.0
MAX_REPAIR_RUN = 3
MAX_REPAIR_FRACTION = 0.01
SAT_RUN = 5
GYRO_MAX_RAD_S = 35.0
DEG_VS_NONE = 0.5
DEG_VS_RAD = 0.2
G_STD = 9.80665
MIN_RATE_HZ = 5.0            # an IMU session sampled slower than 5 Hz is a time base in the wrong unit (1 kHz in ms reads 1 Hz)
MAX_RATE_HZ = 10000.0        # ... and faster than 10 kHz too (s read as ms would give 0.29 MHz)
MAX_DURATION_S = 86400.0     # one day

CHECKS = ("shapes", "length", "time", "nan", "units", "saturation", "mag", "quat", "gyr")


def as_array(source: str, field: str, value, ncols: Optional[int], n: Optional[int] = None) -> np.ndarray:
    """Convert `value` to a float array of shape (n, ncols) (or (n,) when ncols is None).

    Args:
        source: file name for the error message.
        field: field name for the error message.
        value: anything array-like.
        ncols: required number of columns, or None for a 1-D array.
        n: required number of rows, or None for any.
    Returns:
        float64 array (a new array; the input is never modified).
    Raises:
        SessionError: non-numeric content or wrong shape.
    """
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise SessionError(source, field, f"dtype {arr.dtype}", "a numeric array")
    arr = arr.astype(float, copy=True)
    want = "(N,)" if ncols is None else f"(N, {ncols})"
    if ncols is None:
        if arr.ndim == 2 and 1 in arr.shape:
            arr = arr.reshape(-1)
        ok = arr.ndim == 1
    else:
        ok = arr.ndim == 2 and arr.shape[1] == ncols
    if not ok:
        raise SessionError(source, field, f"shape {arr.shape}", f"shape {want}")
    if n is not None and arr.shape[0] != n:
        raise SessionError(source, field, f"{arr.shape[0]} rows", f"{n} rows, one per time stamp")
    return arr


def runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop (exclusive) indices of the runs of True in a 1-D bool mask."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _check_shapes(s: Session) -> None:
    t = as_array(s.source, "t", s.t, None)
    n = t.shape[0]
    for name in ("gyr", "acc", "mag"):
        as_array(s.source, name, getattr(s, name), 3, n)
    if s.quat is not None:
        as_array(s.source, "quat", s.quat, 4, n)
    if s.movement is not None:
        as_array(s.source, "movement", s.movement, None, n)


def _check_length(s: Session) -> None:
    n = int(np.asarray(s.t).shape[0])
    if n == 0:
        raise SessionError(s.source, "t", "0 samples (empty)", f"≥ {MIN_SAMPLES} samples over ≥ {MIN_SECONDS:g} s")
    dur = float(np.nanmax(s.t) - np.nanmin(s.t)) if np.isfinite(s.t).any() else 0.0
    if n >= MIN_SAMPLES and 0 < dur < MIN_SECONDS:        # many samples in a short time: a unit, not a length
        med = float(np.nanmedian(np.diff(np.asarray(s.t, float))))
        if med > 0:
            _check_time_base(s, med, dur)
    if n < MIN_SAMPLES or dur < MIN_SECONDS:
        raise SessionError(s.source, "t", f"{n} samples over {dur:.3g} s (too short)",
                           f"≥ {MIN_SAMPLES} samples over ≥ {MIN_SECONDS:g} s")


def _declared(gaps: Iterable, t0: float, t1: float, tol: float) -> bool:
    for pair in gaps:
        a, b = float(pair[0]), float(pair[1])
        if a <= t0 + tol and b >= t1 - tol:
            return True
    return False


def _check_time(s: Session) -> None:
    t = np.asarray(s.t, float)
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise SessionError(s.source, "t", f"{bad.size} non-finite time stamps (first at index {bad[0]})",
                           "finite times in s")
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size:
        i = back[0]
        raise SessionError(s.source, "t", f"unsorted time stamps: t[{i + 1}] = {t[i + 1]:.6g} s < "
                           f"t[{i}] = {t[i]:.6g} s ({back.size} places)", "strictly increasing times")
    dup = np.flatnonzero(dt == 0)
    if dup.size:
        i = dup[0]
        raise SessionError(s.source, "t", f"duplicate time stamp {t[i]:.6g} s at indices {i} and {i + 1} "
                           f"({dup.size} duplicates)", "strictly increasing times")
    med = float(np.median(dt))
    _check_time_base(s, med, float(t[-1] - t[0]))
    gaps = np.flatnonzero(dt > GAP_STEPS * med)
    declared = s.meta.get("gaps", []) if isinstance(s.meta, dict) else []
    for i in gaps:
        if not _declared(declared, t[i], t[i + 1], 0.5 * med):
            raise SessionError(s.source, "t", f"gap of {dt[i]:.4g} s ({dt[i] / med:.1f} median steps) at "
                               f"t = {t[i]:.4f} s (index {i}; {gaps.size} gaps)",
                               f"steps ≤ {GAP_STEPS:g} × the median step {med:.4g} s, or the gap declared: "
                               "--allow-gaps, load_session(allow_gaps=True) or NPZ key 'gaps' (docs/formats.md)")


def _check_time_base(s: Session, med: float, duration: float) -> None:
    """Median step (s) and duration (s) of a plausible IMU time base: MIN_RATE_HZ ≤ 1/med ≤ MAX_RATE_HZ and
    duration ≤ MAX_DURATION_S. A log stamped in ms read as s (BROAD 06 at 285.7 Hz: step 3.5 "s") fails here."""
    rate = 1.0 / med
    if MIN_RATE_HZ <= rate <= MAX_RATE_HZ and duration <= MAX_DURATION_S:
        return
    raise SessionError(s.source, "t", f"median step {med:.4g} s ({rate:.4g} Hz) over {duration:.6g} s",
                       f"seconds (t in ms? divide by 1000): a rate of {MIN_RATE_HZ:g}–{MAX_RATE_HZ:g} Hz "
                       f"over at most {MAX_DURATION_S / 3600:g} h")


def _repair_nan(s: Session, field: str, x: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, list]:
    """Interpolate short non-finite runs of `x` (N, 3) over `t`; raise on long runs."""
    bad = ~np.all(np.isfinite(x), axis=1)
    if not bad.any():
        return x, []
    start, stop = runs(bad)
    longest = int(np.argmax(stop - start))
    if stop[longest] - start[longest] > MAX_REPAIR_RUN:
        a, b = int(start[longest]), int(stop[longest]) - 1
        raise SessionError(s.source, field, f"NaN/inf run of {b - a + 1} samples at indices {a}..{b} "
                           f"(t = {t[a]:.4f}..{t[b]:.4f} s)",
                           f"finite values (runs of ≤ {MAX_REPAIR_RUN} samples are interpolated)")
    if bad.sum() > MAX_REPAIR_FRACTION * bad.size or bad.all():
        raise SessionError(s.source, field, f"{int(bad.sum())} non-finite samples in {start.size} runs",
                           f"at most {MAX_REPAIR_FRACTION:.0%} of the samples, in runs of ≤ {MAX_REPAIR_RUN}")
    good = ~bad
    fixed = x.copy()
    for j in range(3):
        fixed[bad, j] = np.interp(t[bad], t[good], x[good, j])
    return fixed, np.flatnonzero(bad).tolist()


def _block_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean over each run of k consecutive rows: out[i] = mean(x[i:i+k]); (N−k+1, 3)."""
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    return (c[k:] - c[:-k]) / k


def gyro_unit_evidence(t: np.ndarray, gyr: np.ndarray, acc: np.ndarray, window_s: float = 0.2) -> dict:
    """How well the gyroscope, read as rad/s or as °/s, predicts the turning of the gravity direction.

    A fixed nav-frame vector seen in the body frame moves as b_v(t+T) = Exp(−ω̄T)·b_v(t) (nRb
    propagates as nRb·Exp(ωT)). With â the accelerometer direction averaged over windows of
    `window_s`, each hypothesis c ∈ {1 (rad/s), π/180 (°/s), 0 (no rotation)} predicts
    â(t+T) = Exp(−c·ω̄T)·â(t); the sums of squared prediction errors are compared.

    Args:
        t: (N,) s.  gyr: (N, 3) gyroscope in its unknown unit.  acc: (N, 3) any unit.
        window_s: averaging window and prediction horizon in s.
    Returns:
        {"rad": SSE, "deg": SSE, "none": SSE} (the 'none' hypothesis is the baseline).
    """
    rate = 1.0 / float(np.median(np.diff(t)))
    k = max(1, int(round(window_s * rate)))
    if gyr.shape[0] < 3 * k:
        return {"rad": np.nan, "deg": np.nan, "none": np.nan}
    a_hat = _block_mean(acc, k)
    a_hat = a_hat / np.linalg.norm(a_hat, axis=1, keepdims=True)
    i = np.arange(0, a_hat.shape[0] - k, k)
    w_mid = _block_mean(gyr, k)[i + k // 2]                 # mean rate between the window centres
    T = (t[i + k] - t[i])[:, None]
    out = {}
    for name, c in (("rad", 1.0), ("deg", np.pi / 180.0), ("none", 0.0)):
        pred = np.einsum("nij,nj->ni", expmap(-c * w_mid * T), a_hat[i])
        out[name] = float(np.sum((a_hat[i + k] - pred) ** 2))
    return out


def gyr_robust_max(gyr: np.ndarray) -> float:
    """The units check's statistic (rule (a)): the largest per-axis 99.9th percentile of |gyr| over the finite
    rows, rad/s (also what a simulated body session records, imugraph.io.body_session)."""
    g = np.asarray(gyr, float)
    g = g[np.all(np.isfinite(g), axis=1)]
    return float(np.max(np.percentile(np.abs(g), 99.9, axis=0))) if g.size else float("nan")


def _check_units(s: Session, gyr: np.ndarray, acc: np.ndarray, t: np.ndarray) -> None:
    a_norm = float(np.median(np.linalg.norm(acc, axis=1)))
    if 0.5 <= a_norm <= 2.0:
        raise SessionError(s.source, "acc", f"median |acc| = {a_norm:.3f}: looks like g",
                           "m/s² (≈ 9.81 at rest; multiply g by 9.80665)")
    if not 3.0 <= a_norm <= 40.0:
        raise SessionError(s.source, "acc", f"median |acc| = {a_norm:.4g}", "m/s² (≈ 9.81 at rest)")
    robust_max = gyr_robust_max(gyr)                  # gyr: the finite rows already
    if robust_max > GYRO_MAX_RAD_S:
        raise SessionError(s.source, "gyr", f"robust max |gyr| = {robust_max:.4g} (99.9th percentile): "
                           "looks like deg/s", f"rad/s (≤ {GYRO_MAX_RAD_S:g}; multiply deg/s by π/180)")
    sse = gyro_unit_evidence(t, gyr, acc)
    if sse["deg"] < DEG_VS_NONE * sse["none"] and sse["deg"] < DEG_VS_RAD * sse["rad"]:
        raise SessionError(s.source, "gyr", "read as deg/s the gyro predicts the turning of the gravity direction "
                           f"with {sse['deg'] / sse['none']:.0%} of the no-rotation error, read as rad/s with "
                           f"{sse['rad'] / sse['none']:.0%}: looks like deg/s",
                           "rad/s (multiply deg/s by π/180)")


def _check_saturation(s: Session, field: str, x: np.ndarray, t: np.ndarray) -> None:
    for j, axis in enumerate("xyz"):
        col = x[:, j]
        m = float(np.max(np.abs(col)))
        if m == 0.0:
            continue
        for sign in (1.0, -1.0):
            start, stop = runs(col == sign * m)
            if start.size and int(np.max(stop - start)) >= SAT_RUN:
                k = int(np.argmax(stop - start))
                count = int(np.sum(stop - start))
                raise SessionError(s.source, field, f"axis {axis} saturated: held at {sign * m:.6g} for "
                                   f"{stop[k] - start[k]} consecutive samples from t = {t[start[k]]:.4f} s "
                                   f"({count} samples at the extreme in all)",
                                   "a signal within the sensor's range (no clipped plateaus)")


def _check_mag(s: Session) -> None:
    mag = np.asarray(s.mag, float)
    if np.isinf(mag).any():
        i = int(np.flatnonzero(np.isinf(mag).any(axis=1))[0])
        raise SessionError(s.source, "mag", f"±inf at index {i}", "finite values, or NaN rows for no sample")
    valid = np.all(np.isfinite(mag), axis=1)
    if not valid.any():
        raise SessionError(s.source, "mag", "all NaN (no magnetometer sample)", f"one finite (N, 3) row; {NO_MAG}")
    rows = mag[valid]
    if rows.shape[0] < 2:
        return
    _refuse_dead_axes(s, "mag", rows, "magnetometer", "a field that varies as the sensor turns")


def _refuse_dead_axes(s: Session, field: str, rows: np.ndarray, sensor: str, expected: str) -> None:
    """SessionError naming `field` when `rows` (finite (N, 3), N ≥ 2) hold one value on some axis: a dead or
    disconnected sensor reads all zeros or one frozen value."""
    const = [a for j, a in enumerate("xyz") if np.all(rows[:, j] == rows[0, j])]
    if const:
        what = "all zero" if not np.any(rows) else ("constant " + ("on every axis" if len(const) == 3 else
                                                                   f"on axis {', '.join(const)}"))
        value = ", ".join(f"{a} = {rows[0, 'xyz'.index(a)]:.6g}" for a in const)
        raise SessionError(s.source, field, f"{what} over all {rows.shape[0]} samples ({value}): a dead or "
                           f"disconnected {sensor}", expected)


def _check_gyr(s: Session, gyr: np.ndarray) -> None:
    """Check 8 (module docstring): gyr (finite rows) constant on an axis → SessionError field 'gyr'."""
    if gyr.shape[0] < 2:
        return
    _refuse_dead_axes(s, "gyr", gyr, "gyroscope", "a rate that carries the sensor's noise, even at rest")


def _check_quat(s: Session) -> None:
    if s.quat is None:
        return
    q = np.asarray(s.quat, float)
    ok = np.all(np.isfinite(q), axis=1)
    norms = np.linalg.norm(q[ok], axis=1)
    if norms.size and np.max(np.abs(norms - 1.0)) > 1e-2:
        i = int(np.flatnonzero(ok)[np.argmax(np.abs(norms - 1.0))])
        raise SessionError(s.source, "quat", f"|quat| = {np.linalg.norm(q[i]):.4g} at index {i}",
                           "unit quaternions w,x,y,z (NaN rows where unknown)")


CAL_NORM_RANGE = (0.5, 2.0)      # median |D⁻¹(b_mag − o)| of a calibration applied to its own sensor is ≈ 1


def calibrated_norm_median(session: Session, cal) -> float:
    """Median |m| of the calibrated field m = Calibration.calibrated_field(t, mag) over its finite rows (NaN if none)."""
    m_norm = np.linalg.norm(cal.calibrated_field(session.t, np.asarray(session.mag, float)), axis=1)
    m_norm = m_norm[np.isfinite(m_norm)]
    return float(np.median(m_norm)) if m_norm.size else float("nan")


def check_calibration_applies(session: Session, cal, cal_source: str = "calibration.json") -> float:
    """Refuse a calibration that does not fit this session's magnetometer (one from another sensor).

    The calibrated field m = D⁻¹(y − o) has unit norm for the sensor the calibration was estimated on (Kok &
    Schön's model b_mag = D·bRn·n_mag + o + e with |n_mag| = 1); y is the raw field with the calibration's
    disturbance windows applied (Calibration.corrected), as the smoother sees it. A median |m| outside
    `CAL_NORM_RANGE` means D, o belong to another sensor or unit (BROAD's calibration on Rasteiro's MPU9150:
    field-norm RMS 410 %, orientation 170° off, with no warning before this check).

    Args:
        session: the validated session the calibration is applied to.
        cal: `imugraph.calibration.result.Calibration` (read by io.writers.read_calibration_json).
        cal_source: the calibration's file, for the message.
    Returns:
        The median calibrated norm (≈ 1 when the calibration fits).
    Raises:
        SessionError: field 'calibration', naming the median norm found and the file.
    """
    med = calibrated_norm_median(session, cal)
    if not np.isfinite(med):
        return med
    lo, hi = CAL_NORM_RANGE
    if not lo <= med <= hi:
        raise SessionError(session.source, "calibration", f"median calibrated field norm {med:.3g} with {cal_source} "
                           "(calibration from another sensor?)", f"≈ 1 (between {lo:g} and {hi:g}): a calibration "
                           "of this magnetometer, in its unit")
    return med


def validate_session(session: Session, *, skip: Iterable[str] = ()) -> Session:
    """Check a session; repair isolated NaN samples; never modify the input.

    Args:
        session: the Session to check.
        skip: names of checks to leave out (from `CHECKS`), e.g. ("saturation",) for noise-free
            simulations that hold a constant extreme rate.
    Returns:
        `session` itself when nothing needed repair, else a new Session with repaired gyr/acc and
        ``meta["repaired"] = {"gyr": [indices], "acc": [indices]}``.
    Raises:
        SessionError: the first failed check, naming file, field, found and expected.
    """
    skip = set(skip)
    _check_shapes(session)
    if "length" not in skip:
        _check_length(session)
    t = np.asarray(session.t, float)
    if "time" not in skip:
        _check_time(session)
    gyr, acc = np.asarray(session.gyr, float), np.asarray(session.acc, float)
    repaired: dict = {}
    if "nan" not in skip:
        gyr, repaired["gyr"] = _repair_nan(session, "gyr", gyr, t)
        acc, repaired["acc"] = _repair_nan(session, "acc", acc, t)
    finite = np.all(np.isfinite(gyr), axis=1) & np.all(np.isfinite(acc), axis=1)
    if "units" not in skip:
        _check_units(session, gyr[finite], acc[finite], t[finite])
    if "saturation" not in skip:
        _check_saturation(session, "gyr", gyr[finite], t[finite])
        _check_saturation(session, "acc", acc[finite], t[finite])
    if "mag" not in skip:
        _check_mag(session)
    if "quat" not in skip:
        _check_quat(session)
    if "gyr" not in skip and "saturation" not in skip:     # noise-free simulations skip both (exact plateaus)
        _check_gyr(session, gyr[finite])
    repaired = {k: v for k, v in repaired.items() if v}
    if not repaired:
        return session
    meta = dict(session.meta)
    meta["repaired"] = {**meta.get("repaired", {}), **repaired}
    return replace(session, gyr=gyr, acc=acc, meta=meta)
