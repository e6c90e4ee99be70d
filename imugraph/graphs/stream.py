"""Incremental orientation with a known calibration: the graph of `cpp_smoother.smooth_fixed` ("velocity")
plus the batch model's nav-field perturbation, built keyframe by keyframe and solved by iSAM2 (or, with a
lag, the chain-ordered fixed lag of stream_lag, gtsam's IncrementalFixedLagSmoother or BatchFixedLagSmoother).

One model, two solvers: every closed keyframe interval k → k+1 adds the factors the batch graph holds for it
(imugraph.graphs.cpp_velocity) — the two split super-sample `ImuFactor`s (gyro rows, Huber velocity rows),
the Gauss–Markov bounded-velocity factor, the Huber magnetometer factor on keyframe k's averaged calibrated
field with its full covariance (`MagPoseFactorPose3`; with options.field_sigma against n + d_k, the field
perturbation of calibration.ml's model, `imugraph.graphs.stream_field`), a new gyro-bias segment (prior +
random walk) when the interval starts one — then one `update`. Interval k closes when the first sample of
keyframe k+1 arrives (keyframes every `stride` samples, as `keyframe_layout`): the batch path's preintegration.
As `smooth_fixed` does, the gyro is ω = (I + E)·b_gyr − b (the calibration's gyro map E), the accelerometer is
re-timed by the calibration's δ (`acc_lead_samples`, stream_interval.lead_interval) and the velocity process
σ_v, τ_v is the calibration's (unless StreamOptions sets it). Periodic work (the chain lag's marginalisation
and relinearisation, the online refits) runs on a sample between keyframes, timed apart
(`_between_keyframes`; docs/stream.md "Latency").

Filtered orientation (`push`'s return): the latest estimate of the newest keyframe, carried to the sample
by the gyro integrated since (with the current bias estimate) — available when the sample arrives.
Smoothed orientation (`smoothed()`): at the end, Levenberg–Marquardt on iSAM2's factors from its estimate
(a few relinearising updates first), or with a lag the estimate each keyframe had when it left the window;
per-sample values blended between keyframes as the batch path does (`sample_orientations`).

Arrival problems, all counted in `StreamStats`, none raises: a repeated time stamp is dropped
(`duplicates`); a sample older than the newest one is inserted in time order while its keyframe interval is
still open (`late_inserted`; with a lagging magnetometer the fields re-paired, stream_interval._insert_shifted),
else dropped (`late_dropped`); rows with non-finite gyro or accelerometer
are dropped (`invalid`); a time step over 1.5 nominal steps is a gap (`gaps`, `missing`): the gyro is
integrated across it (held rate) and the covariances grow with the step. A NaN magnetometer row is "no
sample" (lower magnetometer rates); a keyframe interval without one gets no magnetometer factor. Not arrival
problems but caller errors: a rate or a `push` argument of the wrong type or shape raises SessionError naming it;
a nominal rate the first 100 time steps contradict by more than 1.5× warns once (RuntimeWarning, `rate_ratio`).
Online calibration (options.online_calibration): by default the closed-form refit on fixed orientations
(`imugraph.graphs.stream_online`, stream_calib); with calib_states θ = (D, o, dip) is a state of the graph in
every magnetometer factor, pinned at the start calibration, and the streamed calibration is what the data say
about it jointly with the orientations (`imugraph.graphs.stream_calstate`). Gyro bias (per segment) and
gravity are estimated with the orientations.
"""

from __future__ import annotations

import math
import numbers
import time
from array import array
from collections import deque
from dataclasses import replace

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.factors.gaps import gap_steps, keyframe_gap_step
from imugraph.graphs.cpp_velocity import G_KEY, imu_bias_key, pose_key, super_sample_pim
from imugraph.graphs.stream_interval import (NAN3 as _NAN3, Q_ID, ArrivalMixin, bad_row as _bad_row,
                                             interval_preintegration, lead_interval, qmul,
                                             row3 as _row3)
from imugraph.graphs.stream_bridge import bridged_preintegration
from imugraph.graphs.stream_calib import OnlineMagCalibration
from imugraph.graphs.stream_carry import MagCarryMixin
from imugraph.graphs.stream_calstate import CAL_KEY
from imugraph.graphs.stream_field import field_key
from imugraph.graphs.stream_kernels import StepBlocks, linear_step, split_noise_one
from imugraph.graphs.stream_online import OnlineCalibrationMixin
from imugraph.graphs.stream_options import (SIGMA_WEAK_POSE, StreamOptions, StreamStats, acc_lead, make_solver,
                                            velocity_process)
from imugraph.graphs.stream_output import StreamOutputMixin
from imugraph.graphs.stream_position import PositionMixin
from imugraph.graphs.stream_realign import GapRealignMixin
from imugraph.graphs.stream_start import KeyframeStartMixin
from imugraph.graphs.stream_update import KeyframeUpdateMixin

__all__ = ["StreamOptions", "StreamSmoother", "StreamStats"]


class StreamSmoother(OnlineCalibrationMixin, KeyframeStartMixin, ArrivalMixin, StreamOutputMixin, GapRealignMixin,
                     PositionMixin, MagCarryMixin, KeyframeUpdateMixin):
    """Push samples in arrival order; get the filtered orientation of each at once, the smoothed ones at the end.

    Args:
        cal: the calibration (held fixed); rate: nominal sampling rate, Hz; options: `StreamOptions`;
        g0: start value of gravity when options.g is None (default 9.81; `stream_session` passes the
        bootstrap's median |acc|, as the batch path uses the session's).
        weak_scale: s of the batch's weak prior D = s·I (options.calib_weak_prior; `stream_session` passes the
        median |y| of the bootstrap window, as `weak_initial`); None: |det D|^(1/3) of `cal`.
        start_window_s: the stream's first seconds that `cal` was fitted on (the bootstrap window; options.disturb_detect
        learns the field's own variation there, stream_disturb).
    """

    def __init__(self, cal: Calibration, rate: float, options: StreamOptions = StreamOptions(), g0: float = 9.81,
                 weak_scale: float | None = None, start_window_s: float = 0.0):
        if isinstance(rate, bool) or not isinstance(rate, numbers.Real) or not (np.isfinite(rate) and rate > 0):
            raise SessionError("stream", "rate", f"{rate!r} ({type(rate).__name__})", "a positive sampling rate in Hz (a number)")
        if not isinstance(options, StreamOptions):
            raise SessionError("stream", "options", type(options).__name__, "a StreamOptions")
        if options.fixed_lag_solver not in ("batch", "incremental", "chain"):
            raise SessionError("stream", "fixed_lag_solver", repr(options.fixed_lag_solver),
                               '"chain", "incremental" or "batch"')
        self.rate, self.opt = float(rate), options
        self.stride = max(1, int(round(rate / options.keyframe_hz)))
        self._gap_step = keyframe_gap_step(1.0 / rate)    # a longer gap closes the interval (keyframe_layout)
        self._init_realign()                 # gap_realign_s (stream_realign)
        self._init_position()                # position_sigma (stream_position)
        self._mid = self.stride // 2 + 1 if self.stride >= 2 else 0     # see _between_keyframes
        self._chain = options.lag_s is not None and options.fixed_lag_solver == "chain"
        self._maintained = not self._chain   # the chain lag's `maintain` ran in the open interval
        self.stats = StreamStats()
        self._cal0 = replace(cal, mag_delay_s=0.0)       # disturbance windows only; the lag is shifted here
        self._windows = [(float(d["t_start"]), float(d["t_end"])) for d in cal.disturbances]
        self._mag_shift = int(round(cal.mag_delay_s * rate))
        scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
        tau = cal.coverage.get("noise_correlation", {}) if isinstance(cal.coverage, dict) else {}
        self._sig_y = np.asarray(cal.noise.get("mag", np.full(3, 0.01 * scale)), float) * np.sqrt(tau.get("mag", 1.0))
        self._set_calibration(cal)
        # θ = (D, o, δ) a state of the graph (stream_calstate; iSAM2 and the chain lag), else the closed-form refit
        self._calstate = bool(options.online_calibration and options.calib_states and (options.lag_s is None or self._chain))
        self._online = OnlineMagCalibration(cal, options.calib_prior_rel, estimate_dip=options.calib_dip,
                                            use_start_std=options.calib_prior_from_start) if options.online_calibration and not self._calstate else None
        self._init_calstate(cal)
        self._init_disturb(cal, weak_scale, start_window_s)   # causal disturbance windows, the batch's weak prior (stream_online)
        self._pending: deque = deque()       # intervals not yet folded: (k, t_k, kRb (n,3,3), y (n,3))
        self._next_refit, self._refit_due = options.calib_every_s, False   # due: runs between keyframes
        self._hist_y, self._mag_index = [], {}   # iSAM2: per-interval y (keep_history), keyframe → index of its
        #                                          magnetometer factor, for the final re-issue
        self._n_factors = 0
        self._sig_g = np.asarray(cal.noise.get("gyr", np.full(3, 0.005)), float)
        self._sig_acc = np.asarray(cal.noise.get("acc", np.full(3, 0.05)), float)
        self._b_hat = np.asarray(cal.gyro_bias, float)
        E = np.asarray(cal.gyro_map, float)   # ω = (I + E)·b_gyr − b, as smooth --calibration (Calibration.corrected_gyro)
        self._IE = tuple(tuple(float(v) for v in row) for row in np.eye(3) + E) if np.any(E) else None
        self._IE_inv = np.linalg.inv(np.eye(3) + E).T if np.any(E) else None      # rows: w @ this = recorded gyro
        self._sig_v, self._tau_v = velocity_process(options, cal)    # σ_v, τ_v: options', else the calibration's
        self._steps = StepBlocks(self._sig_v, self._tau_v, options.field_sigma, options.field_tau)
        self._lead_n, self._lead_f = acc_lead(options, cal)          # δ = n + f: options', else the calibration's
        self._acc_tail = np.zeros((0, 3))    # the last n accelerometer rows before the open interval
        self._estimate_g = options.g is None
        self._g = float(options.g if options.g is not None else g0)
        self._global_keys = ((G_KEY,) if self._estimate_g else ()) + ((CAL_KEY,) if self._calstate else ())   # re-stamped
        self._pim_params = gtsam.PreintegrationParams.MakeSharedU(self._g)
        self._solver = make_solver(options)   # a failed update is counted and the prediction kept, never a crash
        self._weak_pose = gtsam.noiseModel.Isotropic.Sigma(6, SIGMA_WEAK_POSE)
        self._buf: list = []                 # open interval: rows (t, gyr(3), acc(3), mag(3) or NaN)
        self._k = 0                          # index of the open interval's keyframe
        self._t0, self._t_last = None, -np.inf    # time of keyframe 0, of the newest sample
        self._kf_t = array("d")              # keyframe times (8 bytes each)
        self._nRk = None                     # latest estimate of keyframe k's rotation
        self._v = self._p = np.zeros(3)      # latest estimates of keyframe k's velocity and position
        self._seg = -1                       # newest bias segment
        self._q_open = Q_ID                  # gyro-integrated kRb of the newest sample in keyframe k (floats)
        self._q_nk = None                    # latest estimate of keyframe k's nRb as floats (w, x, y, z)
        self._hist_kRb, self._hist_dR, self._hist_t = [], [], []   # per closed interval: kRb (n,3,3), ΔR, t
        self._hist_gap = []                  # per closed interval: it ends in a gap (Preintegration.gap_end)
        self._smoothed_kf: dict = {}         # fixed lag: keyframe → last estimate inside the window
        self._b_gyr_est = None               # latest gyro-bias estimate (None: the calibration's)
        self._b_now = tuple(float(v) for v in self._b_hat)     # the same as floats, for the filtered output
        self._field = options.field_sigma is not None          # nav-field perturbation d_k (stream_field)
        self._d = np.zeros(3)                # latest estimate of keyframe k's d_k
        self._finished = False
        self._rate_steps: list | None = []   # the first steps seen, to check the nominal rate once (_check_rate)
        self.rate_ratio = None               # median arrived step × rate (1 when the nominal rate is right)
        self._init_end_extensions()          # windows_end, velocity_end, gyro_map_end (stream_output)

    # ------------------------------------------------------------------ arrival
    def push(self, t: float, gyr, acc, mag=None) -> np.ndarray:
        """Add one sample; returns the filtered orientation nRb (4,) w,x,y,z available now (for a dropped
        sample: that of the newest accepted one; NaN before any sample)."""
        try:
            mx, my, mz = _NAN3 if mag is None else _row3(mag)
            row = (float(t), *_row3(gyr), *_row3(acc), mx, my, mz)
        except (TypeError, ValueError):                     # named, as a reader names a bad field (U22 defect 10)
            raise _bad_row(t, gyr, acc, mag) from None
        return np.array(self.push_floats(*row))

    def push_floats(self, t: float, gx: float, gy: float, gz: float, ax: float, ay: float, az: float,
                    mx: float = math.nan, my: float = math.nan, mz: float = math.nan) -> tuple:
        """`push` of one row given as ten Python floats (NaN magnetometer: no sample), the filtered orientation
        as a 4-tuple of floats: the per-sample fast path (`stream_session`; no numpy call per sample — the
        same arithmetic as `push`, whose result is this tuple as an array)."""
        if self._IE is not None:              # (I + E)·b_gyr: the calibration's gyro scale/misalignment
            (a, b, c), (d, e, f), (g, h, i) = self._IE
            gx, gy, gz = a * gx + b * gy + c * gz, d * gx + e * gy + f * gz, g * gx + h * gy + i * gz
        # one sum is finite iff all its terms are (an inf − inf is NaN)
        if self._finished or not math.isfinite(t + gx + gy + gz + ax + ay + az):
            self.stats.invalid += 1
            return self._filtered_q()
        if t <= self._t_last:
            return tuple(self._late((t, gx, gy, gz, ax, ay, az, mx, my, mz)).tolist())
        has_mag = math.isfinite(mx + my + mz)
        if has_mag:
            self.stats.mag_samples += 1
            m = (mx, my, mz)
        else:
            m = _NAN3
        self.stats.accepted += 1
        row = (t, gx, gy, gz, ax, ay, az) + m
        buf = self._buf
        if self._t0 is None:
            self._t0 = t
            self._kf_t.append(t)
        elif len(buf) >= self.stride or t - buf[-1][0] > self._gap_step:
            self._close(row)                    # this sample is keyframe k+1 (after a gap too: keyframe_layout)
            self._t_last = t
            self._buf = [row]
            self._q_open = Q_ID
            self._attach_delayed_mag(m, has_mag)
            return self._filtered_q()
        else:                                 # q_open ⊗ Exp((ω − b)Δt): stream_interval.qstep written out
            prev = buf[-1]
            bx, by, bz = self._b_now
            dt = t - prev[0]
            x, y, z = (prev[1] - bx) * dt, (prev[2] - by) * dt, (prev[3] - bz) * dt
            t2 = x * x + y * y + z * z
            if t2 < 1e-16:
                c, s = 1.0 - t2 / 8.0, 0.5 - t2 / 48.0
            else:
                th = math.sqrt(t2)
                c, s = math.cos(0.5 * th), math.sin(0.5 * th) / th
            self._q_open = qmul(self._q_open, (c, s * x, s * y, s * z))
        self._t_last = t
        buf.append(row)
        if self._mag_shift > 0:
            self._attach_delayed_mag(m, has_mag)
        if self._mid and len(buf) >= self._mid and (self._refit_due or not self._maintained):
            self._between_keyframes()
        return self._filtered_q()

    def _between_keyframes(self) -> None:
        """Periodic work done on the samples between two keyframes (from halfway on), one job per sample, off
        the keyframe updates' latency and timed apart (stats.between_s / between_cpu_s): the chain lag's
        `maintain` (its due marginalisation, which re-eliminates the window, else its relinearisation step;
        stream_lag), then the online calibration's due refit (stream_online: the same data as at the keyframe)."""
        if self._chain and not self._maintained:
            self._maintained = True
            start, start_cpu = time.perf_counter(), time.thread_time()
            due = self._solver.due()
            try:
                left = self._solver.maintain()
            except (RuntimeError, IndexError, ValueError):     # counted; the next keyframe update retries
                self.stats.failed_updates += 1
                left = None
            self._smoothed_kf.update(left or {})
            if left:
                self._forget_smoothed(self._k)
            self.stats.marginal_steps += int(due)
        elif self._refit_due:
            start, start_cpu = time.perf_counter(), time.thread_time()
            self._refit(self._kf_t[-1] - self._t0)
        else:
            return
        self.stats.between_s.append(time.perf_counter() - start)
        self.stats.between_cpu_s.append(time.thread_time() - start_cpu)

    # ------------------------------------------------------------------ keyframes
    def _start_windowed(self, t: np.ndarray, m: np.ndarray) -> tuple:
        """(m at the sample times t with the start disturbance windows applied, whether one overlaps t): Calibration.
        corrected (delay 0: a copy) only where one overlaps, else m itself."""
        hit = any(ts <= t[-1] and te >= t[0] for ts, te in self._windows)
        return (self._cal0.corrected(t, m) if hit else m), hit

    def _close(self, row_next) -> None:
        """Interval k (the buffer) → keyframe k+1 (its first row row_next, at t_next): its factors, then one solver
        update (row_next's rates end a gap's bridge: gap_bridge, stream_bridge)."""
        start, start_cpu = time.perf_counter(), time.thread_time()
        t_next = row_next[0]
        n, k = len(self._buf), self._k
        rows = np.array(self._buf)
        t = np.array([r[0] for r in self._buf] + [t_next])
        w, a, m_raw = rows[:, 1:4], rows[:, 4:7], rows[:, 7:10]
        if self._lead_n or self._lead_f:      # accelerometer timing δ, as smooth_fixed (stream_interval eq. 4)
            w_rec = w if self._IE_inv is None else w @ self._IE_inv
            a, self._acc_tail = lead_interval(t, w_rec, a, self._acc_tail, self._lead_n, self._lead_f)
        steps = t[1:] - t[:-1]
        if self._rate_steps is not None:
            self._check_rate(steps)
        gap = gap_steps(steps, 1.0 / self.rate)          # counted on the interval as accepted (late rows in)
        if gap.any():
            self.stats.gaps += int(gap.sum())
            self.stats.missing += int(np.sum(np.round(steps[gap] * self.rate) - 1))
        # the batch path's preintegration (factors.gyro.preintegrate, factors.velocity.velocity_increments)
        # of this one interval, equal to it (stream_interval)
        noise = (self._b_hat, self._sig_g, self.opt.gyro_rate_error, self._sig_acc, self.opt.acc_rate_error,
                 (self.rate, self.opt.gap_rate_walk, self.opt.gap_acc_walk))
        bridged = bool(self.opt.gap_bridge and gap.any())
        if bridged:                                     # stream_bridge (B1)–(B2)
            pre = bridged_preintegration(t, w, a, row_next[1:4], row_next[4:7], *noise)
        else:
            pre = interval_preintegration(t, w, a, *noise)
        kRb, delta_R, cov, dt_k, dv, sig_dv, q_kRb = pre
        y, hit = self._start_windowed(t[:-1], m_raw)
        ok = ~np.isnan(y[:, 0])
        flagged = self._detector is not None and self._disturb_step(k, t[0], t_next, y, ok, hit)   # stream_disturb
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        if k == 0:
            m_cal = (y - self.cal.o) @ self._D_inv.T
            self._start(graph, values, stamps, kRb, a, m_cal, ok & np.all(np.isfinite(m_cal), axis=1))
        seg = int(np.floor((t[0] - self._t0) / self.opt.bias_segment_s)) if self.opt.bias_segment_s > 0 else 0
        if seg != self._seg:
            self._new_segment(graph, values, seg, t_next - self._t0)
        # gyro and velocity rows of the batch path's super-sample ImuFactor, Gauss–Markov, magnetometer
        # cpp_velocity.super_samples for one interval: ω = Log ΔR / Δt + b̂, a = Δv / Δt
        omega = gtsam.Rot3.Logmap(gtsam.Rot3(delta_R)) / dt_k + self._b_hat
        pim = super_sample_pim(self._pim_params, omega, dv / dt_k, dt_k, self._b_hat)
        ends = (pose_key(k), keys.vel(k), pose_key(k + 1), keys.vel(k + 1), imu_bias_key(seg))
        f = gtsam.ImuFactorWithGravityVector(*ends, G_KEY, pim) if self._estimate_g else gtsam.ImuFactor(*ends, pim)
        rot_at = graph.size()                        # the rotation rows' position (stream_realign)
        for model in split_noise_one(cov, sig_dv, self.opt.acc_huber_k):      # cpp_velocity.split_noise
            graph.add(f.cloneWithNewNoiseModel(model))
        # v_{k+1} = φ v_k + w (stream_interval.gauss_markov_factor); blocks by Δt_k (stream_kernels.StepBlocks)
        graph.add(linear_step(keys.vel(k), keys.vel(k + 1), self._steps.velocity(dt_k)))
        if self._pos_on:                             # bounded position (stream_position eq. K1–K2)
            self._position_interval(graph, values, stamps, k, dt_k, t_next - self._t0)
        if self._field:                              # d_{k+1} = φ_k d_k + w_k (stream_field eq. 2)
            graph.add(linear_step(field_key(k), field_key(k + 1), self._steps.field(dt_k)))
            values.insert(field_key(k + 1), np.exp(-dt_k / self.opt.field_tau) * self._d)
            stamps[field_key(k + 1)] = t_next - self._t0
        kRb_m, y_m, carried = self._with_carry(k, kRb, y)     # mag_carry: the closed interval's late fields (C1)
        if (ok.any() or carried) and not (flagged and self.opt.disturb_orient):
            f_mag = self._mag_factor(k, kRb_m, y_m, no_theta=flagged, into=(graph, values, stamps, t_next - self._t0))
            if self.opt.lag_s is None:               # for the final re-issue (iSAM2 keeps every factor): the index
                # once built — a new window's Δo_w prior goes into `graph` first (stream_offsets.added); indexed
                # before, the re-issue replaced that prior and kept the linearised factor too (BROAD 30: 0.132°)
                self._mag_index[k] = self._n_factors + graph.size()
            graph.add(f_mag)
        # prediction of keyframe k+1 from the latest estimate of keyframe k
        nRk = self._nRk.matrix()
        c = np.array([0.0, 0.0, -self._g]) * dt_k + nRk @ dv
        R_next = nRk @ delta_R
        values.insert(pose_key(k + 1), gtsam.Pose3(gtsam.Rot3(R_next), self._p + self._v * dt_k + 0.5 * c * dt_k))
        values.insert(keys.vel(k + 1), self._v + c)
        if self.opt.lag_s is None or self.opt.fixed_lag_solver != "batch":     # iSAM2 inside
            graph.add(gtsam.PriorFactorPose3(pose_key(k + 1), values.atPose3(pose_key(k + 1)), self._weak_pose))
        if self.opt.gap_realign_s:                   # stream_realign (R1)–(R3), after a gap that starts a keyframe
            self._realign_step(graph, values, k, steps[-1] > self._gap_step, (dv, delta_R, dt_k), R_next, rot_at)
        keep = self._offsets.keep(self._offset_alive) if self._offsets is not None else ()    # stream_offsets
        for key in (pose_key(k + 1), keys.vel(k + 1), imu_bias_key(seg)) + self._global_keys + keep:
            stamps[key] = t_next - self._t0
        self._n_factors += graph.size()
        self._update(graph, values, stamps, k + 1, seg, R_next)
        self._kf_t.append(t_next)
        if self.opt.keep_history:
            self._hist_kRb.append(q_kRb)
            self._hist_dR.append(delta_R)
            self._hist_gap.append(bool(gap[-1]))
            self._hist_t.append(t[:-1])
            if self.opt.lag_s is None:
                self._hist_y.append(y)
                if self.opt.windows_end:             # raw rows, no start windows (stream_windows_end)
                    self._hist_raw.append(m_raw.copy())
        if self._gmap is not None:           # J_k and E's coverage sums (stream_gmap)
            self._gmap.interval(k, t, w, rows[:, 4:7], kRb, delta_R, bridged, a)   # a: re-timed ("exact" keeps it)
        self._keep_tail(t[:-1], kRb, delta_R, k)      # mag_carry (stream_carry)
        self._k = k + 1
        self._maintained = not self._chain
        if self._online is not None:
            self._pending.append((k, self._kf_t[k] - self._t0, kRb, y))
        if self._online is not None or self._calstate:
            self._calibrate(t_next - self._t0)
        self.stats.update_s.append(time.perf_counter() - start)
        self.stats.update_cpu_s.append(time.thread_time() - start_cpu)
