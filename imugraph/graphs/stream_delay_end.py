"""The end-of-stream graph re-estimates the magnetometer's lag behind the gyro on the WHOLE stream
(`StreamOptions.mag_delay_end`, off by default; issue 3, session 19, helper D).

The stream pairs each magnetometer row with the gyro row `shift` = round(τ₀·rate) samples earlier
(`stream_interval.ArrivalMixin._attach_delayed_mag`), τ₀ the start calibration's `mag_delay_s`, estimated on the 30 s
bootstrap. The batch estimates τ on the whole trial (`calibration.initial`: `alignment.estimate_mag_delay` on the
ellipsoid-calibrated field and the gyro minus its bias) and `undelay_magnetometer` moves the field by round(τ/Δt)
rows. On BROAD the two whole-sample shifts differ on 26 (2 vs 3), 32 (3 vs 4) and 34 (3 vs 2); smoothing the stream's
end model with the batch's lag moves 26 0.151 → 0.050° and 32 0.255 → 0.187° from the batch (benchmarks/x19_swap.py).

At `finish` (full iSAM2, keep_history) the whole stream is at hand, so this extension (the FIRST of the end graph's
extensions: windows_end, noise_end, ... then see the re-paired rows):

1. the gyro: the per-sample rates recovered from the kept per-sample rotations of every interval k,

       ω_i Δt_i = Log(kRb_iᵀ kRb_{i+1})  within interval k,   Log(kRb_lastᵀ ΔR_k)  across its end            (1)

   (stream_interval eq. 1 integrates Exp((ω_i − b̂) Δt_i): (1) gives (I + Ê₀) b_gyr − b̂ back to rounding; no raw gyro
   row is kept by default — stream_gmap's "exact" rows exist only in that mode);
2. the field: the stream's rows as it paired them (`_hist_raw`, else `_hist_y`) moved back by the stream's shift s₀
   to the arrival time base, a_j = y_{j − s₀}, calibrated with the end graph's θ (the streamed θ; without θ states the
   start calibration), m̃_j = D⁻¹(a_j − o) (unit norm; the batch's D₀⁻¹(y − o₀) of its ellipsoid fit — the free 3×3
   of eq. T2 absorbs D's rotation, not a distortion); the s₀ rows per interval the stream dropped (below) filled by
   linear interpolation (`fill_short_holes`: left in, they biased τ̂ 0.6–0.9 ms low);
   mag_delay_end="clean": only the rows of the normal state's factors (`_hist_y`: the start windows applied; the
   keyframes without a factor or whose factor carried a causal window's Δo_w, `_mag_okey`, left out) and outside the
   batch detector's windows on the whole stream (calibration.disturbance.detect_windows on |m̃| − 1) — a magnet's
   hard iron left in m̃ misfits [m̃_j]× of eq. T2;
3. τ̂ = estimate_mag_delay(t, m̃, ω) (the batch's estimator and defaults); τ̂ = 0.0 (the estimator's "no clear
   optimum") keeps s₀;
4. when s₁ = round(τ̂·rate) ≠ s₀: the whole stream's concatenated rows re-paired by Δ = s₁ − s₀ rows,

       y'_i = y_{i + Δ}   (NaN past the end),                                                              (2)

   split back into the intervals (`_hist_raw`; `_hist_y` recomputed from it with the start windows as `_close` does,
   else moved by (2) itself), and every exact magnetometer factor of the end graph rebuilt from them (as
   `_final_graph` does; stream_windows_end rebuilds its own from the re-paired `_hist_raw`).
5. mag_delay_end="guarded" (session 19, helper G): τ̂ as with True, but the shift is a discrete model parameter the END
   GRAPH decides: the end graph with s₀'s rows and with s₁'s rows (both rebuilt exact, before the later extensions)
   solved by the end LM from the same start, s₁ kept only if its total cost at its optimum is lower (eq. 3, `_guard`);
   else the stream's rows stay (the final LM then starts at s₀'s optimum). A magnet that comes off biases τ̂ (the
   field's change is read as rotation); the wrong pairing should misfit the gyro-propagated rotations.

calibration.json carries τ̂ as `mag_delay_s` when the end graph used it (`_learned_changes`), so `smooth
--calibration` pairs the rows the same way (undelay_magnetometer: round(τ̂/Δt) rows).

BROAD, 17 trials (docs/stream.md "Session 19, helper D"): 26 (2 → 3) 0.151 → 0.048° and 04 (3 → 2) 0.504 → 0.435°
from the batch, the other 15 bit-identical; mean 0.171 → 0.161°, vs truth 0.646 → 0.643°. The lag sits at 2.5–2.8
samples, at the rounding point: the shift is fragile on both paths.

Not recovered: the rows the stream dropped (each interval's last s₀ fields arrive after it closed, `mag_dropped`,
≈ 10 % at s₀ = 3 / 29 rows per keyframe; docs/stream.md "Session 16"): (2) moves those holes by Δ rows with the data.
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from imugraph.calibration.alignment import estimate_mag_delay
from imugraph.calibration.alignment import shift_rows as move_rows   # eq. (2)
from imugraph.geometry import quat_conj, quat_mul, quat_to_rotvec, rotmat_to_quat

__all__ = ["DelayEnd", "fill_short_holes", "gyro_rates", "move_rows"]


def fill_short_holes(t: np.ndarray, m: np.ndarray, max_rows: int) -> np.ndarray:
    """m (N, 3) with every run of ≤ max_rows NaN rows between two valid rows filled by linear interpolation in t (the
    rows a lagging stream drops at each interval's end, step 2); longer runs (data gaps, left-out windows) stay NaN.
    estimate_mag_delay drops only the windows spanning > 1.5 window lengths; with the holes left in, its τ̂ came out
    0.6–0.9 ms low on BROAD 12/26/32 (benchmarks/d19_lag_segments.py)."""
    m = np.array(m, float)
    bad = ~np.all(np.isfinite(m), axis=1)
    if max_rows <= 0 or not bad.any():
        return m
    edges = np.diff(np.r_[0, bad.astype(int), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    ok = np.flatnonzero(~bad)
    for a, b in zip(starts, stops):
        if a > 0 and b < len(m) and b - a <= max_rows:
            for i in range(3):
                m[a:b, i] = np.interp(t[a:b], t[ok], m[ok, i])
    return m


def gyro_rates(hist_kRb: list, hist_dR: list, hist_t: list, t_end: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (1): (t (N,), ω (N, 3) rad/s) per sample of the closed intervals from their per-sample rotations kRb (as
    unit quaternions, w ≥ 0), each interval's ΔR and the sample times; t_end: the time of the keyframe after the last
    interval (the last row's Δt)."""
    q = np.concatenate(hist_kRb)
    q_next = np.concatenate([np.concatenate([qk[1:], rotmat_to_quat(np.asarray(dR))[None]])
                             for qk, dR in zip(hist_kRb, hist_dR)])
    dq = quat_mul(quat_conj(q), q_next)                           # kRb_iᵀ kRb_{i+1}
    dq = np.where(dq[:, :1] < 0, -dq, dq)                          # the short way (rows are stored with w ≥ 0)
    rotvec = quat_to_rotvec(dq)                                    # Log, eq. (1)
    t = np.concatenate(hist_t)
    dt = np.diff(np.r_[t, t_end])
    return t, rotvec / np.where(dt > 0, dt, np.nan)[:, None]


class DelayEnd:
    """The end-graph extension (graph, values) → (graph, values) of the module docstring. After the call `info` holds
    τ̂, s₀, s₁, whether the rows were re-paired (`applied`) and the CPU time; `tau_s` the lag the end graph used."""

    def __init__(self, sm):
        self.sm = sm
        self.info: dict = {"applied": False}
        self.tau_s: float | None = None          # set when the end graph's rows were re-paired

    def estimate(self) -> float:
        """τ̂ of the whole stream (steps 1–3), s; 0.0 when the estimator finds no clear optimum."""
        sm = self.sm
        n_int = len(sm._hist_kRb)
        t, w = gyro_rates(sm._hist_kRb, sm._hist_dR, sm._hist_t, float(sm._kf_t[n_int]))
        clean = sm.opt.mag_delay_end == "clean"
        if clean:                               # the normal state's factors' rows (module docstring)
            okey = getattr(sm, "_mag_okey", {})
            y = np.concatenate([yk if (k in sm._mag_index and k not in okey) else np.full_like(yk, np.nan)
                                for k, yk in enumerate(sm._hist_y)])
        else:
            y = np.concatenate(self._raw_rows())
        a = move_rows(y, -sm._mag_shift)                          # back on the arrival time base: a_j = y_{j − s₀}
        D, o = self._theta_field()
        m_tilde = fill_short_holes(t, np.linalg.solve(D, (a - o).T).T, sm._mag_shift)   # the dropped rows (step 2)
        if clean:                               # and outside the batch detector's windows on the whole stream
            from imugraph.calibration.disturbance import detect_windows

            for win in detect_windows(t, m_tilde):
                m_tilde[win.start:win.stop] = np.nan
        return float(estimate_mag_delay(t, m_tilde, np.nan_to_num(w)))

    def _theta_field(self) -> tuple[np.ndarray, np.ndarray]:
        """D, o of m̃ (step 2): the end graph's θ (`_end_theta`: the streamed θ with calib_final_theta) when θ is a graph
        state, else the start calibration's. A distorted m̃ = L m misfits [m̃]× A of eq. T2 (L[m]× ≠ [Lm]× A)."""
        sm = self.sm
        if sm._calstate:
            from imugraph.factors.theta import unpack_theta

            D, o, _ = unpack_theta(sm._end_theta())
            return np.asarray(D, float), np.asarray(o, float)
        return np.asarray(sm._cal0.D, float), np.asarray(sm._cal0.o, float)

    def _raw_rows(self) -> list:
        """Per interval: the rows as paired without the start windows (`_hist_raw`, windows_end), else `_hist_y`."""
        sm = self.sm
        raw = getattr(sm, "_hist_raw", None)
        return raw if raw is not None and len(raw) == len(sm._hist_kRb) else sm._hist_y

    def _repaired(self, d: int) -> tuple[list | None, list]:
        """Eq. (2) on the concatenated rows, split back per interval: (new _hist_raw or None, new _hist_y)."""
        sm = self.sm
        lengths = np.cumsum([len(t) for t in sm._hist_t])[:-1]
        raw = getattr(sm, "_hist_raw", None)
        if raw is not None and len(raw) == len(sm._hist_kRb):
            new_raw = np.split(move_rows(np.concatenate(raw), d), lengths)
            new_y = []
            for t, m in zip(sm._hist_t, new_raw):                  # the start windows as `_close` applies them
                y, hit = sm._start_windowed(t, m)
                new_y.append(y if hit else m.copy())
            return new_raw, new_y
        return None, np.split(move_rows(np.concatenate(sm._hist_y), d), lengths)

    def _replace_factors(self, graph: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
        """The end graph with every indexed keyframe's magnetometer factor rebuilt exact from the re-paired rows. This
        extension runs FIRST (attach), so `graph` is `_final_graph()`'s: iSAM2's factors with those factors replaced
        (or, without θ states / refits, iSAM2's own) — both are `_exact_mag_graph` of iSAM2's factors."""
        return self.sm._exact_mag_graph(self.sm._solver.getFactorsUnsafe())

    def _mag_cost(self, graph: gtsam.NonlinearFactorGraph, x: gtsam.Values) -> float:
        """Σ_k of the exact magnetometer factors' cost ½‖r_k‖²_Σk (Huber) at x: the last len(_mag_index) factors of
        `graph` (`_exact_mag_graph` adds them there, one per indexed keyframe)."""
        n = len(self.sm._mag_index)
        return float(sum(graph.at(i).error(x) for i in range(graph.size() - n, graph.size())))

    def _guard(self, graph0, graph1, values) -> tuple[bool, gtsam.Values, gtsam.Values]:
        """mag_delay_end="guarded" (step 5): the shift as a discrete model parameter chosen by the end graph. Both end
        graphs (s₀'s and s₁'s rows, the same factors on the same keys: one averaged magnetometer factor per indexed
        keyframe, whose χ² has 3 degrees of freedom whatever its row count) are solved by the end LM from the same
        start; s₁ is kept only if its total cost at its own optimum is lower,

            F(s) = min_x Σ_f ½‖r_f(x; s)‖²_Σf,     keep s₁  ⇔  F(s₁) < F(s₀)                                  (3)

        (the profile likelihood of s, the log-determinants of the averaged factors' covariances left out: n_k differs by
        at most |Δ| rows of ≈ 29). The magnetometer part of F at each optimum is recorded too. Returns (keep s₁, s₀'s
        optimum, s₁'s optimum). Cost: two end solves here; the final LM then starts at the kept optimum."""
        sm = self.sm
        x0 = sm._final_lm(graph0, values)
        x1 = sm._final_lm(graph1, values)
        f0, f1 = float(graph0.error(x0)), float(graph1.error(x1))
        self.info.update(guard_cost_s0=f0, guard_cost_s1=f1, guard_mag_s0=self._mag_cost(graph0, x0),
                         guard_mag_s1=self._mag_cost(graph1, x1), guard_factors=len(sm._mag_index))
        return f1 < f0, x0, x1

    def __call__(self, graph, values):
        sm = self.sm
        start = time.thread_time()
        try:
            if not (sm.opt.keep_history and sm._mag_index and sm._hist_kRb and len(sm._hist_y) == len(sm._hist_kRb)):
                self.info = {"applied": False, "reason": "no history or no magnetometer factor"}
                return graph, values
            s0 = int(sm._mag_shift)
            tau = self.estimate()
            s1 = int(round(tau * sm.rate))
            self.info = {"applied": False, "tau_s": tau, "start_tau_s": float(sm.cal.mag_delay_s),
                         "shift_start": s0, "shift_end": s1}
            if tau == 0.0 or s1 == s0:
                self.info["reason"] = "no clear optimum" if tau == 0.0 else "same shift"
                return graph, values
            new_raw, new_y = self._repaired(s1 - s0)
            empty = [k for k in sm._mag_index if not np.any(np.all(np.isfinite(new_y[k]), axis=1))]
            if empty:                       # a factor would lose every row: the end graph is left as it is
                self.info["reason"] = f"keyframes {empty[:5]} would have no magnetometer row"
                return graph, values
            old_raw = None if new_raw is None else list(sm._hist_raw)
            old_y = list(sm._hist_y)
            graph0 = self._replace_factors(graph) if sm.opt.mag_delay_end == "guarded" else None
            if new_raw is not None:
                sm._hist_raw[:] = new_raw
            sm._hist_y[:] = new_y
            graph1 = self._replace_factors(graph)
            if graph0 is not None:              # step 5: the end graph decides between s₀ and s₁
                keep1, x0, x1 = self._guard(graph0, graph1, values)
                if not keep1:                   # back to the stream's pairing: the end graph as it came
                    if old_raw is not None:
                        sm._hist_raw[:] = old_raw
                    sm._hist_y[:] = old_y
                    self.info["reason"] = "guard: s₀ fits the end graph better"
                    return graph, x0            # the final LM starts at s₀'s optimum (≈ one iteration)
                values = x1                     # the final LM starts at s₁'s optimum
            self.tau_s = tau
            self.info["applied"] = True
            return graph1, values
        finally:
            self.info["cpu_s"] = time.thread_time() - start


def attach(sm) -> None:
    """Switch the option on for a StreamSmoother (from `_init_end_extensions`): the FIRST end extension."""
    sm._delay_end = DelayEnd(sm)
    sm._end_extensions.insert(0, sm._delay_end)
