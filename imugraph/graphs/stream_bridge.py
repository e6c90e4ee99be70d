"""The rate across a sample drop bridged to the first sample after it (StreamOptions.gap_bridge; task K, issue 3).

Why. The gap model (imugraph.factors.gaps, eq. G1) holds the last gyro rate and specific force across the missing
time τ and trusts them as a random walk W of density q. In the stream the interval that ends in a gap closes when
the first sample after the gap arrives (stream.StreamSmoother._close), so the walk's end value is known too. The
random walk pinned at both ends is a Brownian bridge; its conditional mean is the straight line between the two
measured values and its integral's variance is a quarter of the held value's:

    E[ω(s) | ω(0) = ω_j, ω(Δt) = ω_{j+1}] = ω_j + (ω_{j+1} − ω_j) s/Δt                                  (B1)
    Var[∫₀^τ (W(s) − E W(s)) ds] = q² (τ³/3 − τ³/4) = q² τ³ / 12   per axis                                (B2)

(for a walk started at 0 with W(τ) fixed, Cov = min(s, u) − s u/τ; its double integral is τ³/3 − τ³/4). Over a
0.5 s drop during a fast turn the held rate turned BROAD 06's post-gap keyframe 169° from the truth (docs/gaps.md);
the bridge uses the same model with the one measurement more that the stream already has when it closes the
interval. Causal: nothing later than that first sample is used.

How. Each gap step j (Δt_j > 1.5 T) is cut into m_j = round(Δt_j / T) sub-steps; sub-step i holds the rate (and
the specific force) of (B1) at its midpoint, s = (i + ½) Δt_j / m_j. The dense interval is preintegrated as any
other (stream_interval eq. 2–3, no gap term), then (B2) with τ = Δt (the walk pinned at both measured samples)
is added to Σ_ΔR (q_ω) and σ_Δv² (q_a). Only the real rows' rotations kRb are returned (magnetometer rows, history).
The bridge's end on an interval's last step is the next keyframe's first row as pushed (gyro after the
calibration's map; accelerometer not yet re-timed by δ, which is a fraction of a sample against a gap of many).
"""

from __future__ import annotations

import numpy as np

from imugraph.factors.gaps import gap_steps
from imugraph.graphs.stream_interval import interval_preintegration


def bridge_rows(t: np.ndarray, w: np.ndarray, a: np.ndarray, w_next, a_next, nominal_dt: float):
    """The interval's rows with every gap step cut into sub-steps at the (B1) midpoint values.

    Args:
        t: (n+1,) s, the interval's rows and the next keyframe; w, a: (n, 3) rates and specific forces;
        w_next, a_next: (3,) the next keyframe's first sample (the bridge's end on the last step);
        nominal_dt: T, s.
    Returns:
        (t_d (N+1,), w_d (N, 3), a_d (N, 3), real (n,) indices of the real rows in the dense ones).
    """
    steps = t[1:] - t[:-1]
    gap = gap_steps(steps, nominal_dt)
    w_end = np.vstack([w[1:], np.asarray(w_next, float)[None]])       # ω_{j+1} of every step
    a_end = np.vstack([a[1:], np.asarray(a_next, float)[None]])
    tt, ww, aa, real = [], [], [], []
    for j in range(len(w)):
        real.append(len(tt))
        if not gap[j]:
            tt.append(t[j]); ww.append(w[j]); aa.append(a[j])
            continue
        m = max(1, int(round(steps[j] / nominal_dt)))
        for i in range(m):
            f = (i + 0.5) / m                                           # (B1) at the sub-step's midpoint
            tt.append(t[j] + steps[j] * i / m)
            ww.append(w[j] + (w_end[j] - w[j]) * f)
            aa.append(a[j] + (a_end[j] - a[j]) * f)
    tt.append(t[-1])
    return np.array(tt), np.array(ww), np.array(aa), np.array(real)


def bridged_preintegration(t: np.ndarray, w: np.ndarray, a: np.ndarray, w_next, a_next, b_hat: np.ndarray,
                           sigma_gyr: np.ndarray, kappa: float, sigma_acc: np.ndarray, kappa_a: float, gap: tuple):
    """`stream_interval.interval_preintegration` of an interval with gap steps, the rate and specific force across
    each bridged (B1) to the sample after it, with the variance (B2). gap = (rate, q_ω, q_a). Same returns."""
    rate, q_w, q_a = gap
    t_d, w_d, a_d, real = bridge_rows(t, w, a, w_next, a_next, 1.0 / rate)
    kRb, delta_R, cov, dt_k, dv, sig_dv, q_kRb = interval_preintegration(t_d, w_d, a_d, b_hat, sigma_gyr, kappa,
                                                                         sigma_acc, kappa_a, None)
    # (B2) over the whole gap step Δt: the walk is pinned at the two measured samples that span it (review R3; the
    # held model's τ = Δt − T counts only the time past the nominal step). The sub-steps' white noise is counted as
    # if measured (interval_preintegration, σ_g² per sub-step): understated by ≈ m/2, small against q_ω² Δt³/12.
    st = t[1:] - t[:-1]
    tau3_12 = float(np.sum(np.where(gap_steps(st, 1.0 / rate), st, 0.0) ** 3)) / 12.0   # Σ Δt³/12, (B2)
    cov = cov + q_w**2 * tau3_12 * np.eye(3)
    sig_dv = float(np.sqrt(sig_dv**2 + q_a**2 * tau3_12))
    return kRb[real], delta_R, cov, dt_k, dv, sig_dv, q_kRb[real]
