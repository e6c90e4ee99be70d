"""The sample clock behind a recording's timestamps, from the stamps alone (used by effects/timestamp_jitter.py).

Model (J1): the sensor samples on its own uniform clock; sample j is sensed at τ_j and stamped at t_j,

    τ_j = T₀ + Δ·k_j,   k_j integer, k_{j+1} − k_j ≥ 1 (a step > 1: samples lost on the link),
    t_j = τ_j + d_j,    d_j ≥ 0 the receive delay (buffering, radio/USB scheduling).

Fit (`fit_clock`, from the stamps alone: no residual, no truth, so nothing is fitted to held-out
samples): the period and a tick from the stamps' phase coherence (J5, `clock_period`: a lost sample keeps
the phase, a burst's samples have random phases); the lost samples k by a monotone Viterbi over the
cumulative count D_j = k_j − j with a low-quantile (q = 0.2) pinball cost — most stamps arrive with a small
delay, buffered bursts and late packets are the upper tail —, alternated 4 times with Δ, T₀ refitted by
the quantile regression of t on k:

    cost = Σ_j ρ_q(t_j − T₀ − Δ(j + D_j)) + λ·D_{N−1},   D_j nondecreasing,   λ = Δ/2 per lost sample  (J3)
"""

from __future__ import annotations

import numpy as np

QUANTILE = 0.2               # (J3) the clock runs along this quantile of the stamps' delay
ROUNDS = 4                   # alternations of the clock line and the drops (J3)


def _pinball(r: np.ndarray, q: float) -> np.ndarray:
    return np.where(r >= 0, q * r, (q - 1.0) * r)


def _quantile_line(k: np.ndarray, t: np.ndarray, q: float, iters: int = 30) -> tuple[float, float]:
    """(T₀, Δ) minimising Σ ρ_q(t − T₀ − Δk) by iteratively reweighted least squares (J3)."""
    A = np.c_[np.ones_like(k, dtype=float), k.astype(float)]
    c = np.linalg.lstsq(A, t, rcond=None)[0]
    for _ in range(iters):
        r = t - A @ c
        w = np.where(r >= 0, q, 1.0 - q) / np.maximum(np.abs(r), 1e-6)
        c_new = np.linalg.lstsq(A * np.sqrt(w)[:, None], t * np.sqrt(w), rcond=None)[0]
        if np.allclose(c_new, c, rtol=0, atol=1e-9):
            c = c_new
            break
        c = c_new
    return float(c[0]), float(c[1])


def _drops_viterbi(t: np.ndarray, T0: float, period: float, q: float, d_max: int) -> np.ndarray:
    """(N,) cumulative lost samples D_j (nondecreasing integers in [0, d_max]) minimising (J3)."""
    n = len(t)
    states = np.arange(d_max + 1)
    cost = _pinball(t[0] - T0 - period * states, q)
    back = np.zeros((n, d_max + 1), np.int32)
    for j in range(1, n):
        best = np.minimum.accumulate(cost)                       # best predecessor D' ≤ D
        back[j] = np.maximum.accumulate(np.where(cost <= best, states, 0))
        cost = best + _pinball(t[j] - T0 - period * (j + states), q)
    D = np.zeros(n, np.int64)
    D[-1] = int(np.argmin(cost + 0.5 * period * states))    # λ = Δ/2 per lost sample (Σ increments = D_N−1)
    for j in range(n - 1, 0, -1):
        D[j - 1] = back[j][D[j]]
    return D


def _coherence(f: np.ndarray, t: np.ndarray) -> np.ndarray:
    """C(f) = |Σ_j exp(2πi f t_j)| / N for each f (J5), in blocks (memory 256 × N complex)."""
    out = np.empty(len(f))
    for i in range(0, len(f), 256):
        out[i:i + 256] = np.abs(np.exp(2j * np.pi * np.outer(f[i:i + 256], t)).sum(axis=1)) / max(len(t), 1)
    return out


def clock_period(t: np.ndarray, span=(0.6, 1.5), seg_s: float = 2.0, n_seg: int = 8) -> tuple:
    """(Δ₀, a tick t₀, lock √N·C(f₀)) of the sample clock from the stamps' phase coherence (J5):

        C(f) = |Σ_j exp(2πi f t_j)| / N,   f₀ = argmax_f C(f)                                          (J5)

    A lost sample keeps the phase (the next one is a whole period later) and a burst's samples have random
    phases, so neither biases f₀, where a slope of t over the index counts every lost sample as a period
    (V1000 LSM9DS0: 11.1 ms for a 10 ms clock). Coarse: the sum of C over up to `n_seg` segments of `seg_s`
    spread over the recording, f in span · [(N − 1)/T], grid 0.1/seg_s. Then refined over prefixes of doubling length (41 points within ±0.2/T of
    the previous f₀). The tick from the phase at f₀ (the circular mean of t mod Δ₀). The lock √N·C(f₀) is
    ≈ 1 for phases at random (a Rayleigh variable; its maximum over the grid's ~10³ frequencies ≈ 3); reported
    only (Rasteiro: 3.1–20.8; the Viterbi and the quantile line refine a weakly locked start, §S20-T)."""
    t0_abs = float(np.asarray(t, float)[0])
    t = np.asarray(t, float) - t0_abs
    T = max(float(t[-1]), 1e-9)
    f_med = (len(t) - 1) / T                                  # the mean rate (the median step fails when packets bunch)
    grid = np.arange(span[0] * f_med, span[1] * f_med, max(0.1 / seg_s, (span[1] - span[0]) * f_med / 2e4))
    starts = np.linspace(0.0, max(T - seg_s, 0.0), n_seg)
    segs = [t[(t >= a) & (t < a + seg_s)] for a in starts]
    segs = [x for x in segs if len(x) >= 8] or [t]
    c = sum(_coherence(grid, x - x[0]) for x in segs)
    f0 = float(grid[np.argmax(c)])
    L = seg_s
    while True:
        L = min(2 * L, T)
        x = t[t <= L]
        fine = np.linspace(f0 - 0.4 / L, f0 + 0.4 / L, 41)
        f0 = float(fine[np.argmax(_coherence(fine, x))])
        if L >= T:
            break
    z = np.exp(2j * np.pi * f0 * t).sum()
    return 1.0 / f0, float(t0_abs) + float(np.angle(z)) / (2 * np.pi * f0), float(np.abs(z) / np.sqrt(len(t)))


def fit_clock(t: np.ndarray, q: float = QUANTILE, rounds: int = ROUNDS, candidates: bool = False):
    """The sample clock (J1) behind the stamps t (N,): {"tau": (N,) s, "k": (N,) int, "period": Δ,
    "T0", "lost": samples lost, "deviation": (N,) t − τ, s, "cost": (J3), "lock": (J5)}. Uniform stamps
    (every step within 1e-6 of the median: a recording stamped by its own sample clock) are returned as
    their own clock. candidates: the list of the distinct clocks of the two starts, lowest (J3) first."""
    t = np.asarray(t, float)
    n = len(t)
    j = np.arange(n)
    dt = np.diff(t)
    med = float(np.median(dt)) if n > 1 else 0.0
    if n < 3 or np.max(np.abs(dt - med)) <= 1e-6 * med:
        same = {"tau": t.copy(), "k": j.copy(), "period": med, "T0": float(t[0]), "lost": 0,
                "deviation": np.zeros(n), "lock": float(np.sqrt(n)), "cost": 0.0}
        return [same] if candidates else same
    period, tick, lock = clock_period(t)
    # two starts of (J3), the lower cost kept: the phase-locked clock (J5), and the quantile line over the index
    # (no sample lost) for stamps too bunched to lock a phase (mean delay ≳ 0.9 period)
    T_line, P_line = _quantile_line(j, t, q)
    found = []
    for T_start, P_start in ((tick, period), (T_line, P_line)):
        c, cost = _refine(t, T_start, P_start, q, rounds)
        c.update(lock=lock, cost=cost)
        if not any(np.array_equal(np.diff(c["k"]), np.diff(o["k"])) for o in found):
            found.append(c)
    found.sort(key=lambda c: c["cost"])
    return found if candidates else found[0]


def _refine(t: np.ndarray, tick: float, period: float, q: float, rounds: int) -> tuple[dict, float]:
    """(clock, its (J3) cost) from a start (a tick, a period): the Viterbi of the lost samples alternated
    with the quantile line; the start placed a backlog of periods before the first stamp (bursts)."""
    n = len(t)
    j = np.arange(n)
    dt = np.diff(t)
    t0 = float(t[0])
    backlog = int(max(0.0, np.ceil(np.max(j - (t - t0) / period)))) + 1     # index ahead of the stamps (bursts)
    T0 = tick + period * np.floor((t0 - tick) / period) - period * backlog    # a tick before every sample
    for _ in range(rounds):
        extra = float(np.maximum(0, np.round(dt / period) - 1).sum())
        d_max = int(min(backlog + extra + 10, 5 * n))
        D = _drops_viterbi(t, T0, period, q, d_max)                                  # (J3)
        T0, period = _quantile_line(j + D, t, q)
    k = j + D
    k0 = int(k[0])
    T0 += period * k0
    k = k - k0
    tau = T0 + period * k
    lost = int(k[-1] - (n - 1))
    cost = float(_pinball(t - tau, q).sum()) + 0.5 * period * lost                  # (J3)
    return {"tau": tau, "k": k, "period": period, "T0": T0, "lost": lost, "deviation": t - tau}, cost


def robust_rms(clock: dict) -> float:
    """1.4826·MAD of the stamps' deviation from the clock, in sample periods (the effect's size)."""
    dev = np.asarray(clock["deviation"], float)
    return 1.4826 * float(np.median(np.abs(dev - np.median(dev)))) / max(float(clock["period"]), 1e-12)
