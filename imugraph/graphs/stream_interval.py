"""The per-sample and per-interval arithmetic of a stream (imugraph.graphs.stream), written for speed.

Per sample (`StreamSmoother.push` / `push_floats`: ≈ 75 µs per sample under cProfile before, most of the run time at 286 Hz):
quaternions as tuples of Python floats, w,x,y,z Hamilton (R(p ⊗ q) = R(p) R(q)), no numpy call per sample.

    q ⊗ Exp(θ),   Exp(θ) = (cos(|θ|/2), sin(|θ|/2) θ/|θ|)                                         (1)

Per interval (`StreamSmoother._close`): the gyro preintegration of ONE keyframe interval, equal to
`imugraph.factors.gyro.preintegrate` on it (tests/test_stream_interval.py: to 1e-12), but with the
covariance recursion Σ ← Exp(θ_j)ᵀ Σ Exp(θ_j) + V_j unrolled into one vectorised sum: with R_m = ΔR_{k,m} =
Exp(θ_0)…Exp(θ_{m−1}),

    Σ_ΔR = R_nᵀ (Σ_j R_{j+1} V_j R_{j+1}ᵀ) R_n,   V_j = diag(σ_d² + κ²|ω_j − b̂|²) Δt_j²            (2)

(Forster et al. TRO 2017 eq. 35 and the covariance propagation of gyro.py), and the velocity increment of
`imugraph.factors.velocity.velocity_increments` for the same interval,

    Δv = Σ_j R_j a_j Δt_j,   σ_Δv² = Σ_j (mean σ_a² + κ_a²|a_j|²) Δt_j²                             (3)

The per-sample rotations R_j come from (1) in a Python loop over the interval's samples (a few µs each)
instead of the batch function's padded (L, K) layout, whose fixed cost (≈ 1 ms) dominated for one interval.
Likewise for one interval (issue 3, real-time margin; tests/test_stream_speedpaths.py against the general
functions): `chain` with (1) written out, `q2R` as one quadratic form, the accelerometer re-timing by Rodrigues
on the vector (`turn_back_rows`, eq. 5) and the Gauss–Markov coefficients in scalar arithmetic.
"""

from __future__ import annotations

import math
import warnings

import gtsam
import numpy as np

from imugraph.errors import SessionError
from imugraph.factors.gaps import gap_variance, has_gap



Q_ID = (1.0, 0.0, 0.0, 0.0)
NAN3 = (math.nan, math.nan, math.nan)
_EYE3, _ZERO3, _UNIT3 = np.eye(3), np.zeros(3), gtsam.noiseModel.Unit.Create(3)


def row3(x) -> tuple:
    """Three floats from a 3-vector (array, list, tuple; a (1, 3) array too)."""
    try:
        a, b, c = x.tolist() if isinstance(x, np.ndarray) else x      # tolist: Python floats at once
        return float(a), float(b), float(c)
    except (TypeError, ValueError):
        a, b, c = np.asarray(x, float).reshape(3)
        return float(a), float(b), float(c)


def qmul(p: tuple, q: tuple) -> tuple:
    """Hamilton product p ⊗ q of two float 4-tuples (w, x, y, z)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw)


def qstep(q: tuple, wx: float, wy: float, wz: float, dt: float) -> tuple:
    """q ⊗ Exp((wx, wy, wz)·dt), eq. (1) (series below 1e-8 rad: sin(h)/|θ| ≈ ½ − |θ|²/48)."""
    x, y, z = wx * dt, wy * dt, wz * dt
    t2 = x * x + y * y + z * z
    if t2 < 1e-16:
        c, s = 1.0 - t2 / 8.0, 0.5 - t2 / 48.0
    else:
        t = math.sqrt(t2)
        c, s = math.cos(0.5 * t), math.sin(0.5 * t) / t
    return qmul(q, (c, s * x, s * y, s * z))


def qpos(q: tuple) -> np.ndarray:
    """(4,) array of a float quaternion with w ≥ 0 (the sign convention of `StreamSmoother.push`)."""
    return np.array(q) if q[0] >= 0 else -np.array(q)


def _q2R_map() -> tuple[np.ndarray, np.ndarray]:
    """M (16, 9), c (9,): vec R = vec(q qᵀ) M + c, the entries of
    R = [[1 − 2(y²+z²), 2(xy − wz), 2(xz + wy)], [2(xy + wz), 1 − 2(x²+z²), 2(yz − wx)], [2(xz − wy), 2(yz + wx), 1 − 2(x²+y²)]]
    (geometry.quat_to_rotmat) as linear in the products q_i q_j (index 4i + j, q = w, x, y, z)."""
    M, c = np.zeros((16, 9)), np.array([1.0, 0, 0, 0, 1, 0, 0, 0, 1])
    w, x, y, z = range(4)
    for entry, terms in enumerate([((y, y, -2), (z, z, -2)), ((x, y, 2), (w, z, -2)), ((x, z, 2), (w, y, 2)),
                                   ((x, y, 2), (w, z, 2)), ((x, x, -2), (z, z, -2)), ((y, z, 2), (w, x, -2)),
                                   ((x, z, 2), (w, y, -2)), ((y, z, 2), (w, x, 2)), ((x, x, -2), (y, y, -2))]):
        for i, j, v in terms:
            M[4 * i + j, entry] += v
    return M, c


_Q2R_M, _Q2R_C = _q2R_map()


def q2R(q: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions w,x,y,z → (n, 3, 3) (geometry.quat_to_rotmat without the normalisation): the
    quadratic form of `_q2R_map` as one outer product and one matrix product (4× faster than entry by entry
    for one interval; equal to 1e-15, tests/test_stream_interval.py)."""
    n = len(q)
    return (np.einsum("ni,nj->nij", q, q).reshape(n, 16) @ _Q2R_M + _Q2R_C).reshape(n, 3, 3)


def chain(t: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n+1, 4) quaternions R_0 = I, R_{j+1} = R_j ⊗ Exp((ω_j − b)(t_{j+1} − t_j)), eq. (1); t (n+1,), w (n, 3).
    `qstep` written out in the loop (the same operations in the same order: equal to the bit; 25 % faster)."""
    bx, by, bz = (float(v) for v in b)
    qw, qx, qy, qz = Q_ID
    out = [Q_ID]
    cos, sin, sqrt = math.cos, math.sin, math.sqrt
    tl = t.tolist()
    for (wx, wy, wz), t0, t1 in zip(w.tolist(), tl, tl[1:]):
        d = t1 - t0
        x, y, z = (wx - bx) * d, (wy - by) * d, (wz - bz) * d
        t2 = x * x + y * y + z * z
        if t2 < 1e-16:
            c, s = 1.0 - t2 / 8.0, 0.5 - t2 / 48.0
        else:
            th = sqrt(t2)
            c, s = cos(0.5 * th), sin(0.5 * th) / th
        x, y, z = s * x, s * y, s * z                 # qmul(q, (c, x, y, z))
        qw, qx, qy, qz = (qw * c - qx * x - qy * y - qz * z, qw * x + qx * c + qy * z - qz * y,
                          qw * y - qx * z + qy * c + qz * x, qw * z + qx * y - qy * x + qz * c)
        out.append((qw, qx, qy, qz))
    return np.array(out)


def interval_preintegration(t: np.ndarray, w: np.ndarray, a: np.ndarray, b_hat: np.ndarray, sigma_gyr: np.ndarray,
                            kappa: float, sigma_acc: np.ndarray, kappa_a: float, gap: tuple | None = None):
    """One keyframe interval: samples at t[:n] with rates w (n, 3), specific forces a (n, 3); the next
    keyframe at t[n].

    gap = (rate, q_ω, q_a): steps longer than 1.5/rate hold samples that never arrived, trusted as
    `imugraph.factors.gaps` eq. (G1) says: V_j += q_ω² τ_j³/3 · I, σ_Δv² += q_a² τ_j³/3 (as the batch path).

    Returns:
        kRb (n, 3, 3) = R_j, delta_R (3, 3) = R_n, cov (3, 3) of eq. (2), dt = t[n] − t[0], dv (3,) and
        sigma_dv of eq. (3), kRb_quat (n, 4) (w ≥ 0: the history's rows).
    """
    dt = t[1:] - t[:-1]                           # np.diff
    q = chain(t, w, b_hat)
    Rs = q2R(q)                                   # R_0 … R_n
    wb = w - b_hat
    var = ((np.asarray(sigma_gyr, float) ** 2)[None, :] + kappa**2 * np.einsum("ji,ji->j", wb, wb)[:, None]) \
        * (dt**2)[:, None]                                   # diagonal of V_j
    R1 = Rs[1:]
    S = np.einsum("jik,jlk->il", R1 * var[:, None, :], R1)   # Σ_j R_{j+1} V_j R_{j+1}ᵀ
    Rn = Rs[-1]
    cov = Rn.T @ S @ Rn
    kRb = Rs[:-1]
    dv = np.einsum("jik,jk->i", kRb, a * dt[:, None])
    dt2 = dt * dt
    sa = np.asarray(sigma_acc, float).ravel().tolist()                # mean σ_a² (as np.mean of 3: sum, then / 3)
    var_dv = (sum(x * x for x in sa) / len(sa)) * float(dt2.sum())                       # eq. (3), the two terms
    if kappa_a:
        var_dv += kappa_a**2 * float(np.einsum("ji,ji,j->", a, a, dt2))
    if gap is not None and has_gap(dt, 1.0 / gap[0]):          # gaps eq. (G1), on the steps with missing samples
        tau3 = float(gap_variance(dt, 1.0 / gap[0], 1.0).sum())     # Σ τ_j³/3, scaled by q² below
        # isotropic, so Σ_j R_{j+1} V_j Rᵀ_{j+1} of eq. (2) is Σ_j V_j
        cov = cov + gap[1] ** 2 * tau3 * np.eye(3)
        var_dv += gap[2] ** 2 * tau3
    qk = q[:-1]
    qk = np.where(qk[:, :1] < 0, -qk, qk)
    return kRb, Rn, 0.5 * (cov + cov.T), float(t[-1] - t[0]), dv, float(np.sqrt(max(var_dv, 1e-12))), qk


def gauss_markov_factor(key_k: int, key_next: int, dt_k: float, sigma_v: float, tau_v: float):
    """The bounded-velocity factor of one interval, v_{k+1} − φ v_k ~ N(0, σ_v²(1 − φ²) I), φ = exp(−Δt/τ_v): the
    interval term of `cpp_velocity.gauss_markov_factors` (an exact linear factor), without its v_0 prior.
    φ and σ_w as `imugraph.factors.velocity.gauss_markov`, in scalar arithmetic (one interval per call)."""
    from imugraph.graphs.stream_kernels import linear_step, velocity_blocks

    return linear_step(key_k, key_next, velocity_blocks(dt_k, sigma_v, tau_v))


# the nominal rate is checked once against the median of the first RATE_CHECK_STEPS time steps; off by more than
# RATE_TOLERANCE either way (1.5: the gap rule's factor, factors.gaps.GAP_FACTOR) it warns (ArrivalMixin._check_rate)
RATE_CHECK_STEPS, RATE_TOLERANCE = 100, 1.5


def bad_row(t, gyr, acc, mag) -> SessionError:
    """The SessionError of a `push` whose arguments are not a time and 3-vectors (the first bad one named)."""
    for name, v, n in (("t", t, 1), ("gyr", gyr, 3), ("acc", acc, 3), ("mag", mag, 3)):
        if name == "mag" and v is None:
            continue
        try:
            a = np.asarray(v, float)
            ok = a.size == n and (n == 1 or a.ndim <= 2)
        except (TypeError, ValueError):
            return SessionError("stream", name, f"{type(v).__name__} {v!r:.40}", "numbers" if n == 1 else "3 numbers")
        if not ok:
            return SessionError("stream", name, f"shape {a.shape}", "a number" if n == 1 else "3 values (x, y, z)")
    return SessionError("stream", "sample", repr((t, gyr, acc, mag))[:80], "t, gyr (3), acc (3), mag (3) or None")


class ArrivalMixin:
    """The arrival bookkeeping of `StreamSmoother` (imugraph.graphs.stream) that is not on the per-sample fast
    path: a lagging magnetometer's rows moved back, late samples inserted or dropped (state lives in
    StreamSmoother.__init__; rows are (t, gyr×3, acc×3, mag×3) float tuples)."""

    def _attach_delayed_mag(self, m: tuple, has_mag: bool) -> None:
        """A lagging magnetometer (cal.mag_delay_s) reports what the body saw `shift` samples earlier. The fields
        that arrive with the open interval's first `shift` rows belong to the closed one: dropped (`mag_dropped`),
        but kept in `_head_mag` (one entry per row, NaN: none) so that a late insertion can re-pair (`_insert_shifted`)."""
        if self._mag_shift <= 0:
            return
        self._buf[-1] = self._buf[-1][:7] + NAN3                # its own field arrives `shift` samples later
        i = len(self._buf) - 1 - self._mag_shift
        if i < 0:
            if i == -self._mag_shift:                          # the interval's first row: a new head
                self._head_mag = []
            self._head_mag.append(m)
        if has_mag:
            if i >= 0:
                self._buf[i] = self._buf[i][:7] + m
            else:
                self.stats.mag_dropped += 1

    def _late(self, row: tuple) -> np.ndarray:
        """A sample older than the newest: inserted in time order while its interval is open (with a lagging
        magnetometer its field re-paired, `_insert_shifted`), else dropped; a repeated time stamp is a duplicate."""
        t = row[0]
        times = [r[0] for r in self._buf]
        if t in times or t == self._t_last:
            self.stats.duplicates += 1
        elif self._buf and t > times[0]:
            has_mag = math.isfinite(row[7] + row[8] + row[9])
            p = int(np.searchsorted(times, t))
            if self._mag_shift > 0:
                self._insert_shifted(p, row, has_mag)
            else:
                self._buf.insert(p, row if has_mag else row[:7] + NAN3)
            self.stats.late_inserted += 1
            self.stats.accepted += 1
            self.stats.mag_samples += int(has_mag)
            self._q_open = self._integrate_open()
        else:
            self.stats.late_dropped += 1
        return self._filtered()

    def _insert_shifted(self, p: int, row: tuple, has_mag: bool) -> None:
        """Insert a late row at position p of the open interval when the magnetometer lags by s = `_mag_shift` rows
        (U22 defect 2: such rows were always dropped). The field that arrived with row r belongs to row r − s in
        time order, so the pairing is undone, the row inserted with its own field, and the fields paired again:

            raw_r = head_r (r < s),  raw_r = buf_{r−s}.mag (r ≥ s);   buf'_i.mag = raw'_{i+s}   (NaN: not arrived yet)

        The fields raw'_0 … raw'_{s−1} belong to the closed interval (dropped, `mag_dropped` adjusted by the change)."""
        s, buf = self._mag_shift, self._buf
        n = len(buf)
        head = list(self._head_mag[:min(s, n)])
        raw = head + [NAN3] * (min(s, n) - len(head)) + [r[7:10] for r in buf[:max(n - s, 0)]]
        raw.insert(p, row[7:10] if has_mag else NAN3)
        rows = buf[:p] + [row] + buf[p:]
        self._buf = [r[:7] + (raw[i + s] if i + s <= n else NAN3) for i, r in enumerate(rows)]
        self._head_mag = raw[:s]
        finite = lambda x: math.isfinite(x[0] + x[1] + x[2])       # noqa: E731
        self.stats.mag_dropped += sum(map(finite, raw[:s])) - sum(map(finite, head))

    def _check_rate(self, steps: np.ndarray) -> None:
        """Once RATE_CHECK_STEPS steps have arrived: their median against the nominal step 1/rate. A ratio beyond
        RATE_TOLERANCE either way warns once (RuntimeWarning; `rate_ratio` keeps it): with rate=1000 on 285.7 Hz
        data every step looked like a gap (17141 "gaps", smoothed 1.37 → 2.20°, U22 defect 10) and nothing said so.
        A warning, not an error: a stream cannot know its rate before samples arrive and must not stop mid-flight
        (arrival problems are counted, never raised); a caller who wants an error can turn warnings into errors."""
        self._rate_steps.extend(steps.tolist())
        if len(self._rate_steps) < RATE_CHECK_STEPS:
            return
        dt = float(np.median(self._rate_steps))
        self._rate_steps = None
        self.rate_ratio = dt * self.rate
        if not (1.0 / RATE_TOLERANCE <= self.rate_ratio <= RATE_TOLERANCE):
            warnings.warn(f"stream: field 'rate': found {self.rate:g} Hz given, but the samples arrive every "
                          f"{dt * 1e3:.3g} ms ({1.0 / dt:.4g} Hz); expected the sampling rate of the data (keyframes, "
                          f"gaps and noise use it)", RuntimeWarning, stacklevel=4)

    def _integrate_open(self) -> tuple:
        """The open interval's rotation kRb of its newest sample, integrated again (after a late insertion)."""
        q = Q_ID
        bx, by, bz = self._b_now
        for r0, r1 in zip(self._buf[:-1], self._buf[1:]):
            q = qstep(q, r0[1] - bx, r0[2] - by, r0[3] - bz, r1[0] - r0[0])
        return q



def lead_interval(t: np.ndarray, b_gyr: np.ndarray, b_acc: np.ndarray, tail: np.ndarray, whole: int, frac: float):
    """One interval's accelerometer re-timed as `imugraph.calibration.acc_timing.lead_accelerometer` re-times a
    whole session (δ = whole + frac samples): row i takes the row `whole` samples earlier (`tail`: the stream's
    last `whole` rows before this interval; before the stream's first row, that row repeats, as there), then
    the fractional part rotates it by the turn the body made in frac·Δt_i (acc_timing eq. 3)

        a_i ← Exp(f Δt_i ω_i) a_{i−n},   Δt_i = t_{i+1} − t_i                                       (4)

    with ω_i the gyro row as recorded (before the gyro map, bias not removed: as `acc_timing.with_lead`).
    Causal: the interval closes when keyframe k+1's sample (t[n]) has arrived, so every Δt_i is known.

    Args:
        t: (n+1,) s, the interval's rows and the next keyframe; b_gyr, b_acc: (n, 3) rad/s, m/s²;
        tail: (m, 3), m ≤ whole; whole: n ≥ 0; frac: f in [0, 1).

    Returns:
        ((n, 3) re-timed accelerometer, (min(m + n, whole), 3) tail for the next interval).
    """
    a = np.asarray(b_acc, float)
    if whole:
        both = np.concatenate([tail, a]) if len(tail) else a
        if len(tail) < whole:                       # the stream's first rows: its first row repeats
            both = np.concatenate([np.repeat(both[:1], whole - len(tail), axis=0), both])
        a, tail = both[:len(a)], both[-whole:].copy()
    return turn_back_rows(a, b_gyr, t[1:] - t[:-1], frac), tail                        # eq. (4); Δt as np.diff


def turn_back_rows(b_acc: np.ndarray, b_gyr: np.ndarray, dt: np.ndarray, frac: float) -> np.ndarray:
    """`imugraph.calibration.acc_timing.turn_back` for one interval's rows, a_i ← Exp(θ_i) a_i with
    θ_i = f Δt_i ω_i, by Rodrigues on the vector (no 3×3 matrices; tests/test_stream_acc_timing.py: to 1e-12):

        Exp(θ) a = a + (sin|θ|/|θ|) θ×a + ((1 − cos|θ|)/|θ|²) θ×(θ×a)                               (5)

    (series below |θ|² = 1e-16, as geometry.expmap). A Python loop: 2× faster than the (n, 3, 3) einsum at n ≈ 30."""
    if frac <= 0.0:
        return np.array(b_acc, float)
    out = []
    sin, cos, sqrt = math.sin, math.cos, math.sqrt
    for (ax, ay, az), (wx, wy, wz), d in zip(np.asarray(b_acc, float).tolist(), np.asarray(b_gyr, float).tolist(),
                                             (frac * np.asarray(dt, float)).tolist()):
        x, y, z = wx * d, wy * d, wz * d
        t2 = x * x + y * y + z * z
        if t2 < 1e-16:
            A, B = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
        else:
            th = sqrt(t2)
            A, B = sin(th) / th, (1.0 - cos(th)) / t2
        cx, cy, cz = y * az - z * ay, z * ax - x * az, x * ay - y * ax            # θ×a
        out.append((ax + A * cx + B * (y * cz - z * cy), ay + A * cy + B * (z * cx - x * cz),
                    az + A * cz + B * (x * cy - y * cx)))                         # eq. (5)
    return np.array(out).reshape(-1, 3)
